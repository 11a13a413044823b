"""Inverted lists: a coarse quantizer (k-means, ``nlist`` centres) splits the codes, and a query scans the
``nprobe`` nearest lists. The quantizer is learnt by ``train`` (the explicit step at fit and refit, on the
fitting photos' codes), never from whatever batch happens to be added first."""

from __future__ import annotations

import math

import faiss
import numpy as np

from app.engine.index.base import register_index_kind
from app.engine.index.faiss_index import FaissIndex

#: FAISS wants about this many training points per list.
POINTS_PER_LIST = 39


class IvfIndex(FaissIndex):
    kind = "ivf"

    def __init__(self, dim: int, binary: bool, nlist: int | None = None):
        self.nlist = nlist  # None: sqrt(training points), as many as the training set supports
        super().__init__(dim, binary)

    def _make(self):
        return None  # its lists come from training

    def train(self, x: np.ndarray) -> None:
        x = self._prepare(x)
        n = len(x)
        if n == 0:
            raise ValueError("an IVF index cannot be trained on no codes")
        nlist = self.nlist or max(1, int(math.sqrt(max(n, 1))))
        nlist = max(1, min(nlist, n // POINTS_PER_LIST))
        if self.binary:
            quantizer = faiss.IndexBinaryFlat(self.dim)
            inner = faiss.IndexBinaryIVF(quantizer, self.dim, nlist)
        else:
            quantizer = faiss.IndexFlatIP(self.dim)
            inner = faiss.IndexIVFFlat(quantizer, self.dim, nlist, faiss.METRIC_INNER_PRODUCT)
        inner.own_fields = True
        quantizer.this.disown()
        inner.train(x)
        inner.nprobe = max(1, nlist // 4)
        inner.make_direct_map()
        self._index = (faiss.IndexBinaryIDMap2 if self.binary else faiss.IndexIDMap2)(inner)
        self.tombstones = set()

    def _ivf(self):
        if self._index is None:
            return None
        return faiss.downcast_IndexBinary(self._index.index) if self.binary else faiss.extract_index_ivf(self._index)

    def params(self) -> dict:
        ivf = self._ivf()
        return {
            "nlist": ivf.nlist if ivf is not None else self.nlist,
            "nprobe": ivf.nprobe if ivf is not None else None,
        }


register_index_kind(IvfIndex.kind, IvfIndex)
