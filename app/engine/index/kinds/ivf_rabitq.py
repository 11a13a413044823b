"""A compressed IVF for 10^6-10^7 float references: exact coarse quantizer, RaBitQ codes, exact re-rank.

Why: an exact search over 256-d float codes grows with the collection (docs/benchmarks.md), and keeps 1 KB per
reference in RAM. Following FAISS's guidance for that size, the lists hold compressed codes (RaBitQ by
default: one bit per dimension plus two floats; ``codec`` takes any FAISS factory code, "PQ32", "SQ4", ... for
the bench), and a shortlist of ``shortlist`` ids is re-scored exactly from the float codes
(``FloatCodeTable``: read by ``pread`` from the index's own file, so the float codes are neither a second copy
in RAM nor resident in the process). Fast-scan codes are not offered: FAISS 1.15 cannot remove from their
block-packed lists with a hashtable direct map, and the service deletes live.

The coarse quantizer is exact (a flat scan of the ``nlist`` centroids, cheap at these list counts), not an
HNSW graph: our codes are nearly isotropic (most of the 256 dimensions carry variance), and there an HNSW
over 4,096 centroids searched at efSearch 64 missed the exact nearest list for a share of codes
(``bench.quantizer_assign``); on a real server at 10^6 references some uploaded photos were then not found
by their own /locate, their list being among the query's nearest yet not among the 64 the graph returned
(docs/benchmarks.md). ``quantizer="hnsw"`` keeps the graph for the bench. An index written with the graph
(before the exact quantizer) is served with an exact one over the same centroids when it is loaded: the
lists and their codes stay valid, since the codes are residuals from those centroids.

The region filter: a small region (up to ``exact_filter_max`` ids) is scored exactly from the float codes,
because an IVF scan with an id selector sees only the allowed ids in the ``nprobe`` probed lists and would
miss most of a small region; a larger one is filtered inside the scan by a FAISS id selector.

File: one file per snapshot part, as every kind: a header, FAISS's index, then the float code table.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable
from pathlib import Path

import faiss
import numpy as np

from app.engine.index.base import StagedDump, register_index_kind
from app.engine.index.float_code_table import FloatCodeTable
from app.engine.index.ivf_lists import IvfListsIndex, training_sample, two_level_centroids, usable_nlist

#: Float codes of given ids, in the order asked: a caller that already holds them memory-mapped (the bench's
#: 10^7 synthetic codes) passes this instead of having the index keep its own table.
FloatCodes = Callable[[np.ndarray], np.ndarray]

MAGIC = b"GEOIVFC1"
_HEAD = struct.Struct("<8sQQ")  # magic, FAISS part's bytes, offset of the float code table


class IvfCompressedIndex(IvfListsIndex):
    kind = "ivf-rabitq"

    def __init__(
        self,
        dim: int,
        binary: bool = False,
        nlist: int | None = None,
        nprobe: int = 64,
        shortlist: int = 100,
        codec: str = "RaBitQ",
        quantizer: str = "flat",
        hnsw_m: int = 32,
        ef_search: int = 64,
        exact_filter_max: int = 4096,
        float_codes: FloatCodes | None = None,
    ):
        if binary:
            raise ValueError("ivf-rabitq indexes float codes; binary configurations use binary-ivf")
        if quantizer not in ("flat", "hnsw"):
            raise ValueError(f"quantizer {quantizer!r}: flat or hnsw")
        self.shortlist, self.codec, self.quantizer = shortlist, codec, quantizer
        self.hnsw_m, self.ef_search = hnsw_m, ef_search
        self.exact_filter_max = exact_filter_max
        self.external_codes = float_codes
        self.table = FloatCodeTable(dim)
        super().__init__(dim, False, nlist, nprobe)

    def float_codes(self, ids: np.ndarray) -> np.ndarray:
        return self.table.get(ids) if self.external_codes is None else self.external_codes(ids)

    def _adopt(self, index) -> None:
        super()._adopt(index)
        graph = faiss.downcast_index(index.quantizer)
        if not isinstance(graph, faiss.IndexHNSW):
            return
        if self.quantizer == "hnsw":
            graph.hnsw.efSearch = max(self.ef_search, self.nprobe)
            return
        # An index written with the graph: the same centroids, scanned exactly from now on.
        exact = faiss.IndexFlatIP(index.d)
        exact.add(graph.storage.reconstruct_n(0, graph.ntotal))
        graph.thisown = True  # freed with this proxy: the IVF no longer points to it
        index.quantizer = exact
        exact.thisown = False  # the IVF owns it from now on (own_fields)
        index.own_fields = True

    def set_search(self, nprobe: int, shortlist: int) -> None:
        """Search depth (the bench's sweep); applies to the next search."""
        self.nprobe, self.shortlist = nprobe, shortlist
        if self._index is not None:
            self._adopt(self._index)

    def train(self, x: np.ndarray) -> None:
        """Centroids and code trained on ``x``; replaces any previous index (a refit re-adds afterwards)."""
        x = self._prepare(x)
        if not len(x):
            raise ValueError("an IVF index cannot be trained on no codes")
        nlist = usable_nlist(self.nlist, len(x))
        lists = f"IVF{nlist}_HNSW{self.hnsw_m}" if self.quantizer == "hnsw" else f"IVF{nlist}"
        index = faiss.index_factory(self.dim, f"{lists},{self.codec}", faiss.METRIC_INNER_PRODUCT)
        if isinstance(index, faiss.IndexIVFPQ):
            # The factory turns on polysemous training (minutes, never used here); 64 points per PQ centroid
            # converge for 8-d sub-vectors (with 256, the PQ's k-means was most of the training's time).
            index.do_polysemous_training = False
            index.pq.cp.max_points_per_centroid = 64
        sample = training_sample(x, nlist)
        if nlist >= self.two_level_from:  # the quantizer already holds nlist centroids: train fits the codec
            faiss.extract_index_ivf(index).quantizer.add(two_level_centroids(sample, nlist, spherical=True))
        index.train(sample)
        self.table = FloatCodeTable(self.dim)
        self._adopt(index)

    # -- changes --------------------------------------------------------------------------------------
    def add(self, ids: np.ndarray, x: np.ndarray) -> None:
        super().add(ids, x)
        if self.external_codes is None:
            self.table.put(np.ascontiguousarray(ids, dtype=np.int64), self._prepare(x))

    def remove(self, ids) -> int:
        n = super().remove(ids)
        if self.external_codes is None:
            self.table.drop(np.atleast_1d(np.asarray(ids, np.int64)))
        return n

    def reconstruct(self, ids) -> np.ndarray:
        """The exact float codes (what ``score_ids``, the two-stage re-rank, reads)."""
        return self.float_codes(np.asarray(ids, np.int64)) if len(ids) else np.zeros((0, self.dim), np.float32)

    # -- searching ------------------------------------------------------------------------------------
    def search(self, q: np.ndarray, k: int, allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Top ``k`` per query (scores in [0, 1], ids), best first, -1 padded: the lists give a shortlist of
        ``max(shortlist, k)`` ids, the float codes re-score it exactly."""
        q = self._prepare(q)
        nq = len(q)
        scores = np.zeros((nq, k), np.float32)
        out_ids = np.full((nq, k), -1, np.int64)
        if self._index is None or self._index.ntotal == 0 or k <= 0:
            return scores, out_ids
        params = faiss.SearchParametersIVF(nprobe=self.nprobe)
        if allowed is not None:
            allowed = np.unique(np.asarray(allowed, np.int64))
            if not len(allowed):
                return scores, out_ids
            if len(allowed) <= self.exact_filter_max:
                return self._search_exact(q, k, allowed)
            params.sel = sel = faiss.IDSelectorBatch(allowed)  # noqa: F841 (kept alive for the search)
        _, cand = self._index.search(q, max(self.shortlist, k), params=params)
        for r in range(nq):
            c = cand[r][cand[r] >= 0]
            if not len(c):
                continue
            s = self.float_codes(c) @ q[r]
            order = np.argsort(-s, kind="stable")[:k]
            scores[r, : len(order)] = self._to_scores(s[order])
            out_ids[r, : len(order)] = c[order]
        return scores, out_ids

    def _search_exact(self, q: np.ndarray, k: int, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact scores of the allowed ids that are stored (one hashtable lookup each)."""
        present = np.array([i for i in allowed.tolist() if self._has(i)], np.int64)
        scores = np.zeros((len(q), k), np.float32)
        out_ids = np.full((len(q), k), -1, np.int64)
        if not len(present):
            return scores, out_ids
        s = q @ self.float_codes(present).T
        order = np.argsort(-s, axis=1, kind="stable")[:, :k]
        m = order.shape[1]
        scores[:, :m] = self._to_scores(np.take_along_axis(s, order, axis=1))
        out_ids[:, :m] = present[order]
        return scores, out_ids

    def params(self) -> dict:
        return {
            **super().params(),
            "codec": self.codec,
            "shortlist": self.shortlist,
            "quantizer": self._quantizer_name(),
            "exact_filter_max": self.exact_filter_max,
            "code_bytes": None if self._index is None else int(self._index.code_size),
        }

    def _quantizer_name(self) -> str:
        """What assigns lists in the index served (a loaded snapshot's, which may predate the flat one)."""
        if self._index is None:
            return self.quantizer
        graph = faiss.downcast_index(self._index.quantizer)
        return f"hnsw{graph.hnsw.nb_neighbors(1)}" if isinstance(graph, faiss.IndexHNSW) else "flat"

    # -- files and copies -----------------------------------------------------------------------------
    def copy(self) -> IvfCompressedIndex:
        twin = super().copy()
        twin.table = self.table.copy()
        return twin

    def stage_dump(self, path: Path) -> StagedDump:
        """One file: header, FAISS's index, then the float codes (``FloatCodeTable.write``). FAISS's part is
        streamed into the file now (the caller holds the index's lock: about 114 B per reference); the float
        codes are written by ``finish`` without the lock from a ``copy`` of the table taken now (ids and
        live flags only: the codes stay in their files), and ``adopt`` makes the table read from the new
        file, which frees its spill file of the codes added since the last one."""
        index = self._require_trained()
        f = open(path, "wb")  # noqa: SIM115 (closed by ``finish``)
        try:
            f.write(_HEAD.pack(MAGIC, 0, 0))
            faiss.write_index(index, faiss.PyCallbackIOWriter(f.write))
            faiss_bytes = f.tell() - _HEAD.size
            f.write(b"\0" * (-f.tell() % 8))
            table_at = f.tell()
        except BaseException:
            f.close()
            raise
        # with an external reader the codes live elsewhere: an empty table keeps the file well-formed
        frozen = self.table.copy() if self.external_codes is None else FloatCodeTable(self.dim)

        def finish() -> None:
            with f:
                frozen.write(f)
                f.seek(0)
                f.write(_HEAD.pack(MAGIC, faiss_bytes, table_at))

        def adopt(final: Path) -> None:
            if self.external_codes is None:
                self.table.rebase(FloatCodeTable.read(final, table_at), frozen)

        return StagedDump(finish, adopt)

    def dump(self, path: Path) -> None:
        """``stage_dump`` in one go, written beside ``path`` and renamed over it: truncating a file in place
        would change the float codes under an index that reads them from it."""
        path = Path(path)
        tmp = path.with_name(path.name + ".part")
        staged = self.stage_dump(tmp)
        staged.finish()
        os.replace(tmp, path)  # an open file stays valid whatever becomes of its path
        staged.adopt(path)

    def load(self, path: Path) -> None:
        """Read what ``dump`` wrote: FAISS's part into RAM (streamed from the file: no second copy of its
        bytes), the float codes left in the file (their ids read)."""
        with open(path, "rb") as f:
            magic, faiss_bytes, table_at = _HEAD.unpack(f.read(_HEAD.size))
            if magic != MAGIC:
                raise ValueError(f"{path} is not an {self.kind} index file")
            index = faiss.read_index(faiss.PyCallbackIOReader(_bounded_reader(f, faiss_bytes)))
        if index.d != self.dim:
            raise ValueError(f"{path} holds a {index.d}-d index; this one is {self.dim}-d")
        self._adopt(index)
        self.table = FloatCodeTable.read(Path(path), table_at) if self.external_codes is None else self.table
        if self.external_codes is None and len(self.table.live_ids()) != index.ntotal:
            raise ValueError(f"{path}: {index.ntotal} codes in the lists but a float table of another size")


def _bounded_reader(f, limit: int) -> Callable[[int], bytes]:
    """``f.read`` that never reads past ``limit`` bytes (FAISS's part: a reader asking for more hits the
    float code table's bytes, not an error)."""
    left = [limit]

    def read(n: int) -> bytes:
        data = f.read(min(n, left[0]))
        left[0] -= len(data)
        return data

    return read


register_index_kind(IvfCompressedIndex.kind, IvfCompressedIndex)
