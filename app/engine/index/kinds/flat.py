"""Exact search: every query scans every code. Right up to ~100k references, and what every shipped
configuration uses; removals are dropped in place at compaction."""

from __future__ import annotations

import faiss

from app.engine.index.base import register_index_kind
from app.engine.index.faiss_index import FaissIndex


class FlatIndex(FaissIndex):
    kind = "flat"
    removes_in_place = True

    def _make(self):
        if self.binary:
            return faiss.IndexBinaryIDMap2(faiss.IndexBinaryFlat(self.dim))
        return faiss.IndexIDMap2(faiss.IndexFlatIP(self.dim))

    def params(self) -> dict:
        return {"code_bytes": self.dim // 8 if self.binary else 4 * self.dim}


register_index_kind(FlatIndex.kind, FlatIndex)
