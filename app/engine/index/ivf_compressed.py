"""A compressed IVF index for 10^6-10^7 float references, with an exact re-rank from the stored float codes.

Why: an exact search over 256-d float codes costs 52 ms at 10^6 references and about 0.5 s at 10^7 on one
thread, and keeps 1 KB per reference in RAM. Following FAISS's guidance for 10^6-10^7 vectors, this kind
is an inverted file whose coarse quantizer is an HNSW graph over the centroids (so assigning a query or a
new reference to its lists costs O(log nlist), not O(nlist)), with compressed codes in the lists (PQ,
RaBitQ or SQ: a few tens of bytes per reference), then an exact re-rank of a shortlist. The re-rank reads
the float codes the service's store already keeps for every reference, by id, through ``float_codes``; the
index never holds a second copy of them.

Live changes: a hashtable direct map (id -> list and offset) makes ``remove`` O(1) per id (FAISS swaps
the last entry of the list into the hole) and lets ``add`` replace an id in place; the coarse quantizer is
fixed after ``train``, so an add costs one HNSW search and one encoding whatever the collection's size.
The region filter is a FAISS id selector applied inside the list scan. Fast-scan variants (4-bit PQ, RaBitQ
fast scan) are not offered: FAISS 1.15 cannot remove from their block-packed lists with a hashtable.

``train`` is an explicit step, run at fit and refit on the collection's codes or a sample of them: the
lists are as good as the centroids, and centroids trained on the first batch that happens to arrive
(as ``VectorIndex``'s IVF is) do not follow the collection as it grows.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path

import faiss
import numpy as np

#: Float codes of given ids, (len(ids), dim), in the order asked: the store's copy, read for the re-rank.
FloatCodes = Callable[[np.ndarray], np.ndarray]

#: FAISS warns below 39 training points per list; more than 64 adds time, not quality.
MIN_POINTS_PER_LIST, MAX_POINTS_PER_LIST = 39, 64


def default_nlist(n: int) -> int:
    """About 4 sqrt(n) lists, a power of two (FAISS's guidance: 4-16 sqrt(n)); 1,024 at 10^5, 4,096 at
    10^6, 16,384 at 10^7. More lists scan fewer codes per probe but cost more to train."""
    return max(1, 2 ** round(math.log2(max(4 * math.sqrt(max(n, 1)), 1))))


def training_sample_size(nlist: int) -> int:
    return nlist * MAX_POINTS_PER_LIST


class IvfCompressedIndex:
    """IVF (HNSW coarse quantizer) over compressed codes, inner product, exact re-rank of a shortlist.

    ``codec`` is a FAISS factory code for the lists: "PQ32" (32 bytes), "PQ64", "RaBitQ" (1 bit per
    dimension plus two floats), "SQ4", ... ``float_codes``: where the re-rank reads the exact codes; without
    it the compressed scores are returned as they are (lower accuracy, for measurement)."""

    kind = "ivf-compressed"
    binary = False

    def __init__(
        self,
        dim: int,
        float_codes: FloatCodes | None = None,
        *,
        codec: str = "PQ32",
        nlist: int | None = None,
        nprobe: int = 32,
        shortlist: int = 100,
        hnsw_m: int = 32,
        ef_search: int = 64,
        exact_filter_max: int = 4096,
    ):
        self.dim, self.float_codes, self.codec = dim, float_codes, codec
        self.nlist, self.nprobe, self.shortlist, self.hnsw_m, self.ef_search = (
            nlist,
            nprobe,
            shortlist,
            hnsw_m,
            ef_search,
        )
        self.exact_filter_max = exact_filter_max
        self._owner: faiss.Index | None = None
        self._index: faiss.IndexIVF | None = None

    # -- training -------------------------------------------------------------------------------------
    @property
    def is_trained(self) -> bool:
        return self._index is not None and self._index.is_trained

    def train(self, x: np.ndarray) -> None:
        """Train the centroids and the code on ``x`` (the collection's codes or a sample). Replaces any
        previous index: a refit re-adds the collection afterwards, as a new generation does."""
        x = self._prepare(x)
        nlist = self.nlist or default_nlist(len(x))
        nlist = max(1, min(nlist, len(x) // MIN_POINTS_PER_LIST))
        index = faiss.index_factory(self.dim, f"IVF{nlist}_HNSW{self.hnsw_m},{self.codec}", faiss.METRIC_INNER_PRODUCT)
        ivf = faiss.extract_index_ivf(index)
        if isinstance(ivf, faiss.IndexIVFPQ):
            # The factory turns on polysemous training (codes ordered for Hamming filtering), which we never
            # use and which takes minutes where the PQ itself trains in seconds.
            ivf.do_polysemous_training = False
            # 64 points per PQ centroid instead of 256: 8-d sub-vectors converge with that many, and the PQ's
            # k-means was three quarters of the training time (measured: 216 of 264 s at nlist 1,024).
            ivf.pq.cp.max_points_per_centroid = 64
        if len(x) > training_sample_size(nlist):
            x = x[np.random.default_rng(0).choice(len(x), training_sample_size(nlist), replace=False)]
        index.train(x)
        ivf.set_direct_map_type(faiss.DirectMap.Hashtable)
        self.nlist = nlist
        self._owner, self._index = index, ivf  # the factory's object owns the C++ index; keep it alive
        self._tune()

    def _tune(self) -> None:
        self._index.nprobe = self.nprobe
        faiss.downcast_index(self._index.quantizer).hnsw.efSearch = max(self.ef_search, self.nprobe)

    # -- changes --------------------------------------------------------------------------------------
    def _prepare(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(np.atleast_2d(x), dtype=np.float32)
        if x.shape[1] != self.dim:
            raise ValueError(f"vectors of dimension {x.shape[1]} for an index of {self.dim}")
        return x

    def _require_trained(self) -> faiss.IndexIVF:
        if not self.is_trained:
            raise RuntimeError(f"the {self.kind} index must be trained (at fit or refit) before it is used")
        return self._index

    def add(self, ids: np.ndarray, x: np.ndarray) -> None:
        """Add (or replace) references. An id already present is removed first, so an add is an upsert."""
        index = self._require_trained()
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        x = self._prepare(x)
        if len(ids) != len(x):
            raise ValueError(f"{len(ids)} ids for {len(x)} vectors")
        if len(np.unique(ids)) != len(ids):
            raise ValueError("duplicate ids in one add")
        self.remove(ids)
        index.add_with_ids(x, ids)

    def remove(self, ids) -> int:
        """Remove references at once (one hashtable lookup and one swap per id). Returns how many were there."""
        if self._index is None:
            return 0
        ids = np.ascontiguousarray(np.atleast_1d(np.asarray(ids, dtype=np.int64)))
        if not len(ids):
            return 0
        return int(self._index.remove_ids(faiss.IDSelectorArray(ids)))

    # -- searching ------------------------------------------------------------------------------------
    def search(self, q: np.ndarray, k: int, allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Top ``k`` per query as (scores in [0, 1], ids), best first, ids -1 where fewer exist. The lists
        give a shortlist of ``max(shortlist, k)``; the float codes re-score it exactly. ``allowed``
        restricts the search to those ids (the region filter): a small region (up to ``exact_filter_max``
        ids) is scored exactly from the float codes, because an IVF scan with an id selector only sees the
        allowed ids that fall in the ``nprobe`` probed lists and would miss most of a small region; a larger
        one is filtered inside the scan."""
        q = self._prepare(q)
        nq = len(q)
        scores = np.zeros((nq, k), np.float32)
        out_ids = np.full((nq, k), -1, np.int64)
        if self._index is None or self._index.ntotal == 0 or k <= 0:
            return scores, out_ids
        params = faiss.SearchParametersIVF(nprobe=self.nprobe)
        if allowed is not None:
            allowed = np.ascontiguousarray(allowed, np.int64)
            if not len(allowed):
                return scores, out_ids
            if self.float_codes is not None and len(allowed) <= self.exact_filter_max:
                return self._search_exact(q, k, allowed)
            sel = faiss.IDSelectorBatch(allowed)
            params.sel = sel
        depth = max(self.shortlist, k) if self.float_codes is not None else k
        d, cand = self._index.search(q, depth, params=params)
        for r in range(nq):
            c = cand[r][cand[r] >= 0]
            s = d[r][: len(c)]
            if self.float_codes is not None and len(c):
                s = np.asarray(self.float_codes(c), np.float32) @ q[r]
                order = np.argsort(-s, kind="stable")[:k]
                c, s = c[order], s[order]
            m = min(k, len(c))
            scores[r, :m] = np.clip((1.0 + s[:m]) / 2.0, 0.0, 1.0)
            out_ids[r, :m] = c[:m]
        return scores, out_ids

    def _search_exact(self, q: np.ndarray, k: int, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact scores of the allowed ids that are in the index (one hashtable lookup each)."""
        present = np.array([i for i in np.unique(allowed) if self._has(int(i))], np.int64)
        scores = np.zeros((len(q), k), np.float32)
        out_ids = np.full((len(q), k), -1, np.int64)
        if not len(present):
            return scores, out_ids
        s = q @ np.asarray(self.float_codes(present), np.float32).T
        order = np.argsort(-s, axis=1, kind="stable")[:, :k]
        m = order.shape[1]
        scores[:, :m] = np.clip((1.0 + np.take_along_axis(s, order, axis=1)) / 2.0, 0.0, 1.0)
        out_ids[:, :m] = present[order]
        return scores, out_ids

    def _has(self, ref_id: int) -> bool:
        try:
            self._index.direct_map.get(ref_id)
            return True
        except RuntimeError:
            return False

    # -- contents -------------------------------------------------------------------------------------
    def ids(self) -> np.ndarray:
        if self._index is None:
            return np.zeros(0, np.int64)
        inv = self._index.invlists
        parts = []
        for lst in range(inv.nlist):
            n = inv.list_size(lst)
            if n:
                parts.append(faiss.rev_swig_ptr(inv.get_ids(lst), n).copy())
        return np.sort(np.concatenate(parts)) if parts else np.zeros(0, np.int64)

    @property
    def size(self) -> int:
        return 0 if self._index is None else int(self._index.ntotal)

    # -- persistence ----------------------------------------------------------------------------------
    def dump(self, path: Path) -> None:
        """Write the index to ``path`` (FAISS streams it to the file: no second in-RAM copy), atomically."""
        index = self._require_trained()
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        faiss.write_index(index, str(tmp))
        os.replace(tmp, path)

    def load(self, path: Path) -> None:
        """Read an index written by ``dump``; this object's nprobe and shortlist (the configuration's) apply."""
        index = faiss.read_index(str(path))
        ivf = faiss.extract_index_ivf(index)
        if ivf.d != self.dim:
            raise ValueError(f"{path} holds a {ivf.d}-d index; this one is {self.dim}-d")
        if ivf.direct_map.type != faiss.DirectMap.Hashtable:
            ivf.set_direct_map_type(faiss.DirectMap.Hashtable)
        self._owner, self._index, self.nlist = index, ivf, ivf.nlist
        self._tune()

    def stats(self) -> dict:
        """Kind and parameters, for /ready and /metrics."""
        return {
            "kind": self.kind,
            "codec": self.codec,
            "nlist": self.nlist,
            "nprobe": self.nprobe,
            "shortlist": self.shortlist,
            "exact_filter_max": self.exact_filter_max,
            "code_bytes": None if self._index is None else int(self._index.code_size),
            "hnsw_m": self.hnsw_m,
            "rerank": self.float_codes is not None,
            "trained": self.is_trained,
            "size": self.size,
        }


# The registry is being built on branch i31-index (app/engine/index/base.py, /work/wt/INDEX_PROTOCOL.md);
# once it is merged, register this kind there:
# register_index_kind("ivf-compressed", lambda dim, binary, **params: IvfCompressedIndex(dim, **params))
