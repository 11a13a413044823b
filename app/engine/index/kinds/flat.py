"""Exact search: every query scans every code. Right up to ~100k references, and what every shipped
configuration uses; removals are dropped in place at compaction."""

from __future__ import annotations

import faiss
import numpy as np

from app.engine.index.base import register_index_kind
from app.engine.index.faiss_index import FaissIndex


class FlatIndex(FaissIndex):
    kind = "flat"
    removes_in_place = True

    def _make(self):
        if self.binary:
            return faiss.IndexBinaryIDMap2(faiss.IndexBinaryFlat(self.dim))
        return faiss.IndexIDMap2(faiss.IndexFlatIP(self.dim))

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """Up to ``n`` live codes drawn reproducibly, read by position from the flat storage (one copy of the
        sample; no lookup per id): the training sample of the compressed kind this index switches to."""
        total = self._index.ntotal
        width = self.dim // 8 if self.binary else self.dim
        if not total:
            return np.zeros((0, width), np.uint8 if self.binary else np.float32)
        if self.binary:
            storage = faiss.downcast_IndexBinary(self._index.index)
            codes = faiss.rev_swig_ptr(storage.xb.data(), total * width).reshape(total, width)
        else:
            codes = faiss.rev_swig_ptr(faiss.downcast_index(self._index.index).get_xb(), total * width)
            codes = codes.reshape(total, width)
        positions = np.arange(total)
        if self.tombstones:
            positions = positions[~np.isin(faiss.vector_to_array(self._index.id_map), self._dead())]
        if len(positions) > n:
            positions = np.sort(np.random.default_rng(seed).choice(positions, n, replace=False))
        return codes[positions].copy()

    def params(self) -> dict:
        return {"code_bytes": self.dim // 8 if self.binary else 4 * self.dim}


register_index_kind(FlatIndex.kind, FlatIndex)
