"""FAISS indexes with stable ids: a float one (inner product) and a binary one (Hamming).

Both are wrapped in an ``IDMap2`` so references keep their ids across deletions and rebuilds, and both
give scores in [0, 1] (cosine mapped to (1 + cos) / 2; 1 - Hamming / bits) so callers can threshold one
way whatever the mode. Flat is exact and right up to ~100k references; IVF and HNSW trade a little recall
for speed beyond that. Deletions become tombstones that searches skip (removing a vector from a flat index moves
every vector after it, a cost that grows with the collection); ``compact`` drops them on a copy when a
snapshot is written, off the request path.
"""

from __future__ import annotations

import math
import os

import faiss
import numpy as np

# One query at a time is the service's load: FAISS's OpenMP threads would only fight onnxruntime's and
# OpenBLAS's for the cores (measured: a 0.05 ms flat search took 3-7 ms after the CNN ran). Batch jobs
# that search many queries at once may raise it with GEOLOC_FAISS_THREADS.
faiss.omp_set_num_threads(int(os.environ.get("GEOLOC_FAISS_THREADS", "1")))

FLOAT_KINDS = ("flat", "ivf", "hnsw")
BINARY_KINDS = ("flat", "ivf", "hnsw")


class VectorIndex:
    """One FAISS index (float or binary) plus the tombstones that HNSW needs."""

    def __init__(self, dim: int, binary: bool, kind: str = "flat", hnsw_m: int = 32, nlist: int | None = None):
        if kind not in FLOAT_KINDS:
            raise ValueError(f"unknown index kind {kind!r}; choose one of {FLOAT_KINDS}")
        if binary and dim % 8:
            raise ValueError("binary codes need a multiple of 8 bits")
        self.dim, self.binary, self.kind, self.hnsw_m, self.nlist = dim, binary, kind, hnsw_m, nlist
        self.tombstones: set[int] = set()
        self._index = None  # built lazily: IVF needs training data before its first add

    # -- building -------------------------------------------------------------------------------------
    def _make(self, train: np.ndarray):
        n = len(train)
        nlist = self.nlist or max(1, int(math.sqrt(max(n, 1))))
        nlist = max(1, min(nlist, n // 39))  # FAISS wants ~39 training points per list
        if self.binary:
            if self.kind == "flat":
                inner = faiss.IndexBinaryFlat(self.dim)
            elif self.kind == "hnsw":
                inner = faiss.IndexBinaryHNSW(self.dim, self.hnsw_m)
            else:
                quantizer = faiss.IndexBinaryFlat(self.dim)
                inner = faiss.IndexBinaryIVF(quantizer, self.dim, nlist)
                inner.own_fields = True
                quantizer.this.disown()
                inner.train(train)
                inner.nprobe = max(1, nlist // 4)
                inner.make_direct_map()
            return faiss.IndexBinaryIDMap2(inner)
        if self.kind == "flat":
            inner = faiss.IndexFlatIP(self.dim)
        elif self.kind == "hnsw":
            inner = faiss.IndexHNSWFlat(self.dim, self.hnsw_m, faiss.METRIC_INNER_PRODUCT)
            inner.hnsw.efSearch = 64
        else:
            quantizer = faiss.IndexFlatIP(self.dim)
            inner = faiss.IndexIVFFlat(quantizer, self.dim, nlist, faiss.METRIC_INNER_PRODUCT)
            inner.own_fields = True
            quantizer.this.disown()
            inner.train(train)
            inner.nprobe = max(1, nlist // 4)
            inner.make_direct_map()
        return faiss.IndexIDMap2(inner)

    def _prepare(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(x)
        if self.binary:
            x = np.ascontiguousarray(x, dtype=np.uint8)
            if x.shape[1] * 8 != self.dim:
                raise ValueError(f"binary codes of {x.shape[1] * 8} bits for an index of {self.dim}")
        else:
            x = np.ascontiguousarray(x, dtype=np.float32)
            if x.shape[1] != self.dim:
                raise ValueError(f"vectors of dimension {x.shape[1]} for an index of {self.dim}")
        return x

    def add(self, ids: np.ndarray, x: np.ndarray) -> None:
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        x = self._prepare(x)
        if self._index is None:
            self._index = self._make(x)
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

    def compact(self) -> None:
        """Drop tombstoned vectors for good (done on a copy, off the request path, when a snapshot is written).
        Flat indexes remove them in place; IVF and HNSW, which cannot, are rebuilt from their live codes once
        the dead weight passes 20 %, else keep their tombstones."""
        if not self.tombstones or self._index is None:
            return
        dead = np.fromiter(self.tombstones, np.int64, len(self.tombstones))
        if self.kind == "flat":
            self._index.remove_ids(faiss.IDSelectorBatch(dead))
            self.tombstones = set()
        elif self.needs_rebuild:
            live = self.ids()
            fresh = VectorIndex.rebuild(self, live, self.reconstruct(live))
            self._index, self.tombstones = fresh._index, set()

    @property
    def ntotal(self) -> int:
        """Live vectors (tombstones excluded)."""
        return 0 if self._index is None else self._index.ntotal - len(self.tombstones)

    @property
    def needs_rebuild(self) -> bool:
        return bool(self.tombstones) and len(self.tombstones) > 0.2 * max(self._index.ntotal, 1)

    def ids(self) -> np.ndarray:
        if self._index is None:
            return np.zeros(0, np.int64)
        all_ids = faiss.vector_to_array(self._index.id_map)
        if not self.tombstones:
            return all_ids
        return all_ids[~np.isin(all_ids, np.fromiter(self.tombstones, np.int64, len(self.tombstones)))]

    def reconstruct(self, ids) -> np.ndarray:
        """Stored vectors (codes) of ``ids``, in order."""
        if not len(ids):
            return np.zeros((0, self.dim // 8), np.uint8) if self.binary else np.zeros((0, self.dim), np.float32)
        if not self.binary:  # one call into FAISS: the two-stage re-rank reads ~100 of these per query
            return self._index.reconstruct_batch(np.ascontiguousarray(ids, dtype=np.int64))
        return np.stack([self._index.reconstruct(int(i)) for i in ids])  # binary IDMap2 has no batch call

    # -- searching ------------------------------------------------------------------------------------
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
        if self._index is None or self.ntotal == 0 or k <= 0:
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
            ok &= ~np.isin(ids, np.fromiter(self.tombstones, np.int64, len(self.tombstones)))
        for r in range(nq):
            keep = np.flatnonzero(ok[r])[:k]
            scores[r, : len(keep)], out_ids[r, : len(keep)] = s[r, keep], ids[r, keep]
        return scores, out_ids

    def score_ids(self, q: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Exact scores of one query against given ids (the re-rank step of a two-stage search)."""
        codes = self.reconstruct(ids)
        if self.binary:
            qb = np.unpackbits(self._prepare(q)[0])
            d = (np.unpackbits(codes, axis=1) != qb).sum(axis=1)
            return self._to_scores(d)
        return self._to_scores(codes @ self._prepare(q)[0])

    # -- persistence ----------------------------------------------------------------------------------
    def to_bytes(self) -> bytes:
        if self._index is None:
            return b""
        ser = faiss.serialize_index_binary if self.binary else faiss.serialize_index
        return ser(self._index).tobytes()

    def load_bytes(self, data: bytes, tombstones=()) -> None:
        if not data:
            self._index = None
        else:
            de = faiss.deserialize_index_binary if self.binary else faiss.deserialize_index
            self._index = de(np.frombuffer(data, dtype=np.uint8))
        self.tombstones = set(int(t) for t in tombstones)

    def memory_bytes_per_vector(self) -> float:
        """Bytes one reference costs in this index (serialised size / count): what bench reports."""
        return len(self.to_bytes()) / max(self.ntotal, 1)

    @classmethod
    def rebuild(cls, template: VectorIndex, ids: np.ndarray, codes: np.ndarray) -> VectorIndex:
        """A fresh index of the same kind from stored codes: drops tombstones, retrains IVF."""
        fresh = cls(template.dim, template.binary, template.kind, template.hnsw_m, template.nlist)
        if len(ids):
            fresh.add(ids, codes)
        return fresh
