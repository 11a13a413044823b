"""HNSW graph: sub-linear search with no training, at the cost of a graph (``m`` links a vector) and of
removals kept as tombstones (a graph cannot drop a node) until compaction re-adds the live vectors."""

from __future__ import annotations

import faiss

from app.engine.index.base import register_index_kind
from app.engine.index.faiss_index import FaissIndex


class HnswIndex(FaissIndex):
    kind = "hnsw"

    def __init__(self, dim: int, binary: bool, m: int = 32, ef_search: int = 64):
        self.m, self.ef_search = m, ef_search
        super().__init__(dim, binary)

    def _make(self):
        if self.binary:
            return faiss.IndexBinaryIDMap2(faiss.IndexBinaryHNSW(self.dim, self.m))
        inner = faiss.IndexHNSWFlat(self.dim, self.m, faiss.METRIC_INNER_PRODUCT)
        inner.hnsw.efSearch = self.ef_search
        return faiss.IndexIDMap2(inner)

    def params(self) -> dict:
        return {"m": self.m, "ef_search": self.ef_search if not self.binary else None}


register_index_kind(HnswIndex.kind, HnswIndex)
