"""What the FAISS-backed kinds share: stable ids, [0, 1] scores, tombstones, the region filter, files.

Every kind is wrapped in an ``IDMap2`` so references keep their ids across deletions and rebuilds.
Deletions become tombstones that searches skip (removing a vector from a flat index moves every vector
after it, a cost that grows with the collection); ``compact`` drops them on a copy when a snapshot is
written, off the request path. A kind module subclasses ``FaissIndex`` with its ``_make`` (the FAISS
index it wraps) and registers itself (``app.engine.index.base.register_index_kind``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import faiss
import numpy as np

from app.engine.index.base import IndexNotTrained, StagedDump, checked_codes

#: FAISS's OpenMP threads when nothing says otherwise. One query at a time is the service's load: more
#: threads would only fight onnxruntime's and OpenBLAS's for the cores (measured: a flat search right after the
#: CNN ran took many times as long as alone). ``Settings.faiss_threads`` sets it for a process (``set_search_threads``).
DEFAULT_SEARCH_THREADS = 1

faiss.omp_set_num_threads(DEFAULT_SEARCH_THREADS)


def set_search_threads(n: int) -> None:
    """FAISS's thread count is process state: the process that owns the settings sets it once."""
    faiss.omp_set_num_threads(max(1, int(n)))


class FaissIndex:
    """One FAISS index (float or binary) with stable ids plus the tombstones of removed ids."""

    kind: ClassVar[str]
    #: Whether ``compact`` may remove vectors in place (flat: one array); else the live ones are re-added.
    removes_in_place: ClassVar[bool] = False
    #: Positions stay in the store: a region is searched as the ids the store finds in it.
    holds_positions: ClassVar[bool] = False

    def __init__(self, dim: int, binary: bool):
        if binary and dim % 8:
            raise ValueError("binary codes need a multiple of 8 bits")
        self.dim, self.binary = dim, binary
        self.tombstones: set[int] = set()
        self._index = self._make()

    # -- the kind's part ------------------------------------------------------------------------------
    def _make(self) -> Any:
        """The ``IDMap2``-wrapped FAISS index, or None for a kind that is made by ``train``."""
        raise NotImplementedError

    def params(self) -> dict[str, Any]:
        """The kind's parameters, for ``stats``."""
        return {}

    # -- training -------------------------------------------------------------------------------------
    @property
    def is_trained(self) -> bool:
        return self._index is not None and bool(self._index.is_trained)

    def train(self, x: np.ndarray) -> None:
        if not self.is_trained:
            self._index.train(self._prepare(x))

    # -- changes --------------------------------------------------------------------------------------
    def _prepare(self, x: np.ndarray) -> np.ndarray:
        return checked_codes(x, self.dim, self.binary)

    def add(self, ids: np.ndarray, x: np.ndarray) -> None:
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        x = self._prepare(x)
        if not self.is_trained:
            raise IndexNotTrained(
                f"the {self.kind} index needs training before references are added: fit or refit the pipeline "
                "(`geoloc fit` / `geoloc refit`), which trains it on the fitting photos' codes"
            )
        self.tombstones.difference_update(int(i) for i in ids)
        self._index.add_with_ids(x, ids)

    def remove(self, ids) -> int:
        """Mark ids dead (tombstones): searches skip them at once, and ``compact`` drops them later. Removing
        in place would move every vector after them (a flat index is one array), a cost that grows with the
        collection on every single deletion. Returns how many ids were newly marked."""
        before = len(self.tombstones)
        if self._index is not None:
            self.tombstones.update(i for i in (int(i) for i in ids) if i not in self.tombstones and self._has(i))
        return len(self.tombstones) - before

    def _has(self, ref_id: int) -> bool:
        """Whether the id is stored (IDMap2 keeps an id -> position hash: one lookup, whatever the size)."""
        try:
            self._index.reconstruct(ref_id)
            return True
        except RuntimeError:
            return False

    def removed_ids(self) -> np.ndarray:
        return np.sort(self._dead())

    def _dead(self) -> np.ndarray:
        """The tombstones, unordered (what every search with tombstones filters by)."""
        return np.fromiter(self.tombstones, np.int64, len(self.tombstones))

    @property
    def compaction_due(self) -> bool:
        return bool(self.tombstones) and (self.removes_in_place or self.needs_rebuild)

    @property
    def needs_rebuild(self) -> bool:
        return bool(self.tombstones) and len(self.tombstones) > 0.2 * max(self._index.ntotal, 1)

    def compact(self) -> None:
        """Drop tombstoned vectors for good. Flat indexes remove them in place; the others, which cannot,
        are emptied (keeping what training learnt) and given their live vectors again once the dead weight
        passes 20 %, else keep their tombstones."""
        if not self.tombstones or self._index is None:
            return
        if self.removes_in_place:
            self._index.remove_ids(faiss.IDSelectorBatch(self._dead()))
            self.tombstones = set()
        elif self.needs_rebuild:
            live = self.ids()
            codes = self.reconstruct(live)
            self._index.reset()
            self.tombstones = set()
            if len(live):
                self._index.add_with_ids(self._prepare(codes), live)

    # -- reading --------------------------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Live vectors (tombstones excluded)."""
        return 0 if self._index is None else self._index.ntotal - len(self.tombstones)

    def ids(self) -> np.ndarray:
        if self._index is None:
            return np.zeros(0, np.int64)
        all_ids = faiss.vector_to_array(self._index.id_map)
        if not self.tombstones:
            return all_ids
        return all_ids[~np.isin(all_ids, self._dead())]

    def reconstruct(self, ids) -> np.ndarray:
        """Stored vectors (codes) of ``ids``, in order."""
        if not len(ids):
            return np.zeros((0, self.dim // 8), np.uint8) if self.binary else np.zeros((0, self.dim), np.float32)
        if not self.binary:  # one call into FAISS: the two-stage re-rank reads ~100 of these per query
            return self._index.reconstruct_batch(np.ascontiguousarray(ids, dtype=np.int64))
        return np.stack([self._index.reconstruct(int(i)) for i in ids])  # binary IDMap2 has no batch call

    def _to_scores(self, d: np.ndarray) -> np.ndarray:
        if self.binary:
            return 1.0 - d.astype(np.float32) / self.dim
        return np.clip((1.0 + d) / 2.0, 0.0, 1.0).astype(np.float32)

    def search(self, q: np.ndarray, k: int, allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Top ``k`` per query as (scores, ids), best first, ids -1 where fewer exist. ``allowed`` restricts
        the search itself to those ids (a region) through a FAISS id selector. Tombstoned ids are skipped by
        over-fetching as many extra results as there are tombstones (compaction keeps that number small)."""
        q = self._prepare(q)
        nq = len(q)
        scores = np.zeros((nq, k), np.float32)
        out_ids = np.full((nq, k), -1, np.int64)
        if self._index is None or self.size == 0 or k <= 0:
            return scores, out_ids
        kk = min(k + len(self.tombstones), self._index.ntotal)
        if allowed is not None:
            allowed = np.ascontiguousarray(allowed, np.int64)
            if len(allowed) == 0:
                return scores, out_ids
            params = faiss.SearchParameters(sel=faiss.IDSelectorBatch(allowed))
            d, ids = self._index.search(q, kk, params=params)
        else:
            d, ids = self._index.search(q, kk)
        s = self._to_scores(d)
        ok = ids >= 0
        if self.tombstones:
            ok &= ~np.isin(ids, self._dead())
        for r in range(nq):
            keep = np.flatnonzero(ok[r])[:k]
            scores[r, : len(keep)], out_ids[r, : len(keep)] = s[r, keep], ids[r, keep]
        return scores, out_ids

    def score_ids(self, q: np.ndarray, ids: np.ndarray) -> np.ndarray:
        codes = self.reconstruct(ids)
        if self.binary:
            qb = np.unpackbits(self._prepare(q)[0])
            d = (np.unpackbits(codes, axis=1) != qb).sum(axis=1)
            return self._to_scores(d)
        return self._to_scores(codes @ self._prepare(q)[0])

    def stats(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "binary": self.binary,
            "dim": self.dim,
            "trained": self.is_trained,
            "size": self.size,
            "tombstones": len(self.tombstones),
            **self.params(),
        }

    # -- files and copies -----------------------------------------------------------------------------
    def copy(self) -> FaissIndex:
        twin = object.__new__(type(self))
        twin.__dict__.update(self.__dict__)
        twin.tombstones = set(self.tombstones)
        if self._index is not None:  # under the collection's lock: one memory copy for float codes
            if self.binary:  # FAISS cannot clone a binary IDMap2: through its serialised form
                twin._index = faiss.deserialize_index_binary(self._serialize())
            else:
                twin._index = faiss.clone_index(self._index)
        return twin

    def _serialize(self) -> np.ndarray:
        return (faiss.serialize_index_binary if self.binary else faiss.serialize_index)(self._index)

    def dump(self, path: Path) -> None:
        if self._index is None:
            raise IndexNotTrained(f"the {self.kind} index was never trained: nothing to write")
        (faiss.write_index_binary if self.binary else faiss.write_index)(self._index, str(path))

    def stage_dump(self, path: Path) -> StagedDump:
        """FAISS streams the whole index into the file (no serialised copy in memory): all of it now."""
        self.dump(path)
        return StagedDump()

    def load(self, path: Path) -> None:
        """Read what ``dump`` (or the service before the index seam: the same FAISS files) wrote."""
        self._index = (faiss.read_index_binary if self.binary else faiss.read_index)(str(path))
        self.tombstones = set()

    def memory_bytes_per_vector(self) -> float:
        """Bytes one reference costs in this index (serialised size / count): what bench reports."""
        return 0.0 if self._index is None else len(self._serialize()) / max(self.size, 1)
