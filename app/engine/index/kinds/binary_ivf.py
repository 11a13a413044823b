"""A binary IVF (Hamming) for the binary configurations at 10^6-10^7 references.

Why: the binary configurations keep Hamming search (32 bytes per reference at 256 bits), but an exhaustive
Hamming scan still grows with the collection (ten times the references, ten times the time). An
inverted file over binary centroids scans ``nprobe`` lists only. The codes are stored whole (32 bytes is
already small), so the only approximation is which lists are scanned. Live changes as in ``ivf-rabitq``
(``IvfListsIndex``: hashtable direct map, removal in place).
"""

from __future__ import annotations

import faiss
import numpy as np

from app.engine.index.base import register_index_kind
from app.engine.index.ivf_lists import IvfListsIndex, training_sample, two_level_centroids, usable_nlist


class BinaryIvfIndex(IvfListsIndex):
    """``faiss.IndexBinaryIVF`` with a flat binary coarse quantizer; scores 1 - Hamming / bits."""

    kind = "binary-ivf"

    def __init__(
        self, dim: int, binary: bool = True, nlist: int | None = None, nprobe: int = 64, exact_filter_max=4096
    ):
        if not binary:
            raise ValueError("binary-ivf indexes binary codes; float configurations use ivf-rabitq")
        self.exact_filter_max = exact_filter_max
        super().__init__(dim, True, nlist, nprobe)

    def train(self, x: np.ndarray) -> None:
        """Binary centroids trained on ``x``; replaces any previous index (a refit re-adds afterwards)."""
        x = self._prepare(x)
        if not len(x):
            raise ValueError("an IVF index cannot be trained on no codes")
        nlist = usable_nlist(self.nlist, len(x))
        quantizer = faiss.IndexBinaryFlat(self.dim)
        index = faiss.IndexBinaryIVF(quantizer, self.dim, nlist)
        index.own_fields = True
        quantizer.this.disown()
        sample = training_sample(x, nlist)
        if nlist >= self.two_level_from:
            # as FAISS's binary training does: k-means on the bits as -1/+1 floats, centroids back to their signs
            signs = np.unpackbits(sample, axis=1).astype(np.float32) * 2 - 1
            quantizer.add(np.packbits(two_level_centroids(signs, nlist, spherical=False) > 0, axis=1))
        index.train(sample)
        self._adopt(index)

    def search(self, q: np.ndarray, k: int, allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Top ``k`` per query as (1 - Hamming / bits, ids), best first, -1 padded.

        ``allowed`` (the region filter): FAISS 1.15's ``IndexBinaryIVF`` refuses id selectors, so a region of
        up to ``exact_filter_max`` ids is scored exactly from its stored codes (read through the direct map),
        and a larger one filters an over-fetched result (which may then hold fewer than ``k``)."""
        q = self._prepare(q)
        nq = len(q)
        scores = np.zeros((nq, k), np.float32)
        out_ids = np.full((nq, k), -1, np.int64)
        if self._index is None or self._index.ntotal == 0 or k <= 0:
            return scores, out_ids
        if allowed is not None:
            allowed = np.unique(np.asarray(allowed, np.int64))
            if not len(allowed):
                return scores, out_ids
            if len(allowed) <= self.exact_filter_max:
                return self._search_exact(q, k, allowed)
        depth = k if allowed is None else min(self._index.ntotal, 8 * k)
        d, i = self._index.search(q, depth, params=faiss.SearchParametersIVF(nprobe=self.nprobe))
        for r in range(nq):
            keep = i[r] >= 0
            if allowed is not None:
                keep &= np.isin(i[r], allowed)
            keep = np.flatnonzero(keep)[:k]
            scores[r, : len(keep)], out_ids[r, : len(keep)] = self._to_scores(d[r, keep]), i[r, keep]
        return scores, out_ids

    def _search_exact(self, q: np.ndarray, k: int, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        present = np.array([i for i in allowed.tolist() if self._has(i)], np.int64)
        scores = np.zeros((len(q), k), np.float32)
        out_ids = np.full((len(q), k), -1, np.int64)
        if not len(present):
            return scores, out_ids
        bits = np.unpackbits(self.reconstruct(present), axis=1)
        d = (np.unpackbits(q, axis=1)[:, None, :] != bits[None]).sum(axis=2)
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        m = order.shape[1]
        scores[:, :m] = self._to_scores(np.take_along_axis(d, order, axis=1))
        out_ids[:, :m] = present[order]
        return scores, out_ids

    def params(self) -> dict:
        return {**super().params(), "exact_filter_max": self.exact_filter_max, "code_bytes": self.dim // 8}


register_index_kind(BinaryIvfIndex.kind, BinaryIvfIndex)
