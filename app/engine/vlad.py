"""Codebooks and VLAD aggregation (MBVLAD: mini-batch k-means codebook, thesis chapter 3).

VLAD sums, per codeword, the residuals of the descriptors assigned to it; signed power-law damps bursty
repeated structures (windows, bricks), intra-normalisation stops one codeword dominating, and the final
L2 makes inner product a cosine. ``kmeans`` (Lloyd's) is kept as the plain baseline the thesis compares
against; ``minibatch`` is Sculley's algorithm, cheaper and more stable across re-runs.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from app.engine.artifacts import data_hash, load_artifact, save_artifact

CODEBOOK_KIND, CODEBOOK_VERSION = "codebook", 1


class Codebook:
    def __init__(self, centers: np.ndarray, algorithm: str = "minibatch", manifest: dict | None = None):
        self.centers = np.ascontiguousarray(centers, dtype=np.float32)
        self.algorithm = algorithm
        self.manifest = manifest or {}
        self._sq_norms = (self.centers**2).sum(axis=1)

    @property
    def k(self) -> int:
        return len(self.centers)

    @property
    def dim(self) -> int:
        return self.centers.shape[1]

    @classmethod
    def fit(
        cls,
        descriptors: np.ndarray,
        k: int,
        algorithm: str = "minibatch",
        seed: int = 0,
        max_iter: int = 100,
        batch_size: int = 10_000,
    ) -> Codebook:
        """``max_iter`` counts mini-batch steps for ``minibatch`` (the thesis: 100 steps of large batches)
        and Lloyd iterations for ``kmeans``."""
        from sklearn.cluster import KMeans, MiniBatchKMeans  # fitting only: serving never pays its import

        x = np.ascontiguousarray(descriptors, dtype=np.float32)
        k = min(k, len(x))
        if algorithm == "minibatch":
            epochs = max(1, math.ceil(max_iter * batch_size / len(x)))  # scikit-learn counts epochs
            km = MiniBatchKMeans(
                n_clusters=k,
                batch_size=batch_size,
                max_iter=epochs,
                n_init=3,
                random_state=seed,
                reassignment_ratio=0.01,
            )
        elif algorithm == "kmeans":
            km = KMeans(n_clusters=k, n_init=1, max_iter=max_iter, random_state=seed)
        else:
            raise ValueError(f"unknown codebook algorithm {algorithm!r}")
        km.fit(x)
        manifest = {
            "k": k,
            "algorithm": algorithm,
            "seed": seed,
            "n_train": len(x),
            "data_hash": data_hash(x),
            "inertia": float(km.inertia_),
        }
        return cls(km.cluster_centers_, algorithm, manifest)

    def assign(self, x: np.ndarray) -> np.ndarray:
        """Nearest codeword per descriptor (squared Euclidean, computed as a matrix product)."""
        d = self._sq_norms[None, :] - 2.0 * (x @ self.centers.T)
        return np.argmin(d, axis=1)

    def save(self, directory: Path, name: str = "codebook") -> None:
        save_artifact(
            directory,
            name,
            CODEBOOK_KIND,
            CODEBOOK_VERSION,
            {"algorithm": self.algorithm},
            {"centers": self.centers},
            {"fit": self.manifest},
        )

    @classmethod
    def load(cls, directory: Path, name: str = "codebook") -> Codebook:
        manifest, arrays = load_artifact(directory, name, CODEBOOK_KIND, CODEBOOK_VERSION)
        return cls(arrays["centers"], manifest["params"]["algorithm"], manifest.get("fit"))


def vlad(descriptors: np.ndarray, codebook: Codebook, alpha: float = 0.5, intra_norm: bool = True) -> np.ndarray:
    """(N, D) descriptors -> (k * D,) VLAD vector: residual sums, signed power-law ``alpha`` (1 = off),
    optional intra-normalisation, then L2. No descriptors give the zero vector."""
    k, d = codebook.k, codebook.dim
    out = np.zeros((k, d), np.float32)
    if len(descriptors):
        x = np.asarray(descriptors, np.float32)
        a = codebook.assign(x)
        onehot = np.zeros((k, len(x)), np.float32)
        onehot[a, np.arange(len(x))] = 1.0
        out = onehot @ x  # residual sums as one matrix product: far faster than a scatter-add
        counts = onehot.sum(axis=1)
        out -= counts[:, None] * codebook.centers
    if alpha != 1.0:
        out = np.sign(out) * np.abs(out) ** alpha
    if intra_norm:
        norms = np.linalg.norm(out, axis=1, keepdims=True)
        out = np.divide(out, norms, out=np.zeros_like(out), where=norms > 0)
    flat = out.ravel()
    n = np.linalg.norm(flat)
    return flat / n if n > 0 else flat
