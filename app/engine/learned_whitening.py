"""Learned whitening from the collection's own GPS pairs (Radenovic, Tolias and Chum, TPAMI 2018).

Why: PCA-whitening equalises the variance of every direction the aggregated vectors vary in, whether that
variation tells places apart or only follows light, viewpoint and clutter. The collection says which of its
references show the same place (their GPS tags, within ``pos_radius_m`` of each other), so the directions
along which *matching* pairs differ can be shrunk and those along which *non-matching* pairs differ
kept: whiten by the covariance of matching-pair differences, then rotate by the principal directions of
the non-matching pairs' differences in that whitened space, keeping the ``dim`` most discriminative.

The aggregated vectors are long (tens of thousands of dimensions) and a collection has a few hundred
references, so the vectors are first projected on their leading principal components (unwhitened,
``pre_dim`` of them, at most n - 1) and the pair covariance is shrunk towards a scaled identity
(``shrinkage``): with a few thousand pairs among a few hundred images it is far from full rank.
The result is one linear map, applied like ``PcaWhitening`` (centre, project, L2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine.artifacts import data_hash, load_artifact, save_artifact
from app.engine.errors import ModelNotReady
from app.engine.geo import haversine_m
from app.engine.pca import l2_normalize

LW_KIND, LW_VERSION = "learned-whitening", 1
#: Pairs this close are treated as one capture (a photo and its crops share their GPS tag exactly): they
#: teach nothing about viewpoint and would dominate the matching pairs, so they are not positives.
SAME_CAPTURE_M = 1.0


@dataclass(frozen=True)
class Place:
    """Where a fitting photo was taken, and its capture (rows of one capture are never a positive pair)."""

    lat: float
    lon: float
    group: str | None = None


def gps_pairs(
    places: Sequence[Place | None], pos_radius_m: float, neg_radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """(positive pairs, negative pairs) as (P, 2) index arrays, i < j: positives lie within ``pos_radius_m``
    of each other (not one capture: the same group, or within ``SAME_CAPTURE_M``), negatives farther than
    ``neg_radius_m``. Photos without a place take part in neither."""
    known = np.array([i for i, p in enumerate(places) if p is not None], dtype=np.intp)
    if len(known) < 2:
        return np.zeros((0, 2), np.intp), np.zeros((0, 2), np.intp)
    lat = np.array([places[i].lat for i in known])
    lon = np.array([places[i].lon for i in known])
    groups = np.array([places[i].group or f"#{i}" for i in known], dtype=object)
    d = haversine_m(lat[:, None], lon[:, None], lat[None, :], lon[None, :])
    iu, ju = np.triu_indices(len(known), k=1)
    dij = d[iu, ju]
    same = (groups[iu] == groups[ju]) | (dij < SAME_CAPTURE_M)
    pos = (dij <= pos_radius_m) & ~same
    neg = dij > neg_radius_m
    return (
        np.stack([known[iu[pos]], known[ju[pos]]], axis=1),
        np.stack([known[iu[neg]], known[ju[neg]]], axis=1),
    )


def _pair_covariance(y: np.ndarray, pairs: np.ndarray, chunk: int = 20_000) -> np.ndarray:
    """Mean outer product of the pairs' differences, in chunks (tens of thousands of pairs)."""
    c = np.zeros((y.shape[1], y.shape[1]), np.float64)
    for s in range(0, len(pairs), chunk):
        p = pairs[s : s + chunk]
        diff = y[p[:, 0]] - y[p[:, 1]]
        c += diff.T @ diff
    return c / max(len(pairs), 1)


class LearnedWhitening:
    """Centre, project by the learned map, L2-normalise: the interface of ``PcaWhitening``."""

    def __init__(self, mean: np.ndarray, projection: np.ndarray, manifest: dict | None = None):
        self.mean = np.asarray(mean, np.float32)
        self._projection = np.ascontiguousarray(projection, dtype=np.float32)  # (D, dim)
        self.manifest = manifest or {}

    @property
    def dim(self) -> int:
        return self._projection.shape[1]

    @classmethod
    def fit(
        cls,
        x: np.ndarray,
        places: Sequence[Place | None],
        dim: int,
        pos_radius_m: float = 25.0,
        neg_radius_m: float = 100.0,
        pre_dim: int = 512,
        shrinkage: float = 0.1,
    ) -> LearnedWhitening:
        """Fit on the aggregated vectors ``x`` (N, D) of photos at ``places`` (None where unknown)."""
        x = np.asarray(x, np.float64)
        if len(places) != len(x):
            raise ValueError(f"{len(x)} vectors but {len(places)} places")
        pos, neg = gps_pairs(places, pos_radius_m, neg_radius_m)
        if len(pos) < 2 or len(neg) < 2:
            raise ModelNotReady(
                f"learned whitening needs matching and non-matching pairs of geotagged photos: found "
                f"{len(pos)} pairs within {pos_radius_m:g} m and {len(neg)} beyond {neg_radius_m:g} m"
            )
        mean = x.mean(axis=0)
        xc = x - mean
        # Leading principal directions of the sample (the SVD of the thin N x D matrix: N is small).
        _, s, vt = np.linalg.svd(xc, full_matrices=False)
        keep = int(min(pre_dim, len(x) - 1, int((s > s[0] * 1e-6).sum())))
        basis = vt[:keep]  # (keep, D)
        y = xc @ basis.T  # (N, keep)
        cs = _pair_covariance(y, pos)
        cs += shrinkage * (np.trace(cs) / keep) * np.eye(keep)
        w_s, v_s = np.linalg.eigh(cs)
        whiten = (v_s / np.sqrt(np.maximum(w_s, 1e-12))) @ v_s.T  # C_S^(-1/2), symmetric
        cd = _pair_covariance(y @ whiten, neg)
        w_d, v_d = np.linalg.eigh(cd)
        order = np.argsort(w_d)[::-1]
        out_dim = min(dim, keep)
        rotate = v_d[:, order[:out_dim]]  # (keep, dim): the most discriminative directions first
        projection = basis.T @ (whiten @ rotate)  # (D, dim)
        manifest = {
            "dim": out_dim,
            "pre_dim": keep,
            "n_train": len(x),
            "input_dim": x.shape[1],
            "positive_pairs": len(pos),
            "negative_pairs": len(neg),
            "pos_radius_m": pos_radius_m,
            "neg_radius_m": neg_radius_m,
            "shrinkage": shrinkage,
            "data_hash": data_hash(x.astype(np.float32)),
        }
        return cls(mean, projection, manifest)

    def transform(self, x: np.ndarray) -> np.ndarray:
        """(N, D) or (D,) -> learned-whitened, L2-normalised (N, dim) or (dim,)."""
        return l2_normalize((np.asarray(x, np.float32) - self.mean) @ self._projection)

    def save(self, directory: Path, name: str = "whitening") -> None:
        save_artifact(
            directory,
            name,
            LW_KIND,
            LW_VERSION,
            {},
            {"mean": self.mean, "projection": self._projection},
            {"fit": self.manifest},
        )

    @classmethod
    def load(cls, directory: Path, name: str = "whitening") -> LearnedWhitening:
        manifest, a = load_artifact(directory, name, LW_KIND, LW_VERSION)
        return cls(a["mean"], a["projection"], manifest.get("fit"))
