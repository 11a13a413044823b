"""PCA-whitening of aggregated vectors, then L2.

Why: VLAD vectors are long (k x D) and their dimensions are correlated; projecting on the leading
principal components and equalising their variance (whitening) both shrinks the code and improves
retrieval (Jégou & Chum 2012). Full whitening on a few hundred training vectors amplifies noisy trailing
components, so the eigenvalue exponent ``power`` (0.5 = full whitening, 0 = plain PCA) is a parameter.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.engine.artifacts import data_hash, load_artifact, save_artifact

PCA_KIND, PCA_VERSION = "pca-whitening", 1


def l2_normalize(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


class PcaWhitening:
    def __init__(
        self,
        mean: np.ndarray,
        components: np.ndarray,
        variances: np.ndarray,
        power: float = 0.5,
        manifest: dict | None = None,
    ):
        self.mean = mean.astype(np.float32)
        self.components = np.ascontiguousarray(components, dtype=np.float32)  # (dim, D)
        self.variances = variances.astype(np.float32)
        self.power = power
        self.manifest = manifest or {}
        scale = np.power(np.maximum(self.variances, 1e-12), -power).astype(np.float32)
        self._projection = np.ascontiguousarray((self.components * scale[:, None]).T)  # (D, dim)

    @property
    def dim(self) -> int:
        return len(self.components)

    @classmethod
    def fit(cls, x: np.ndarray, dim: int, power: float = 0.5, seed: int = 0) -> PcaWhitening:
        from sklearn.decomposition import PCA  # fitting only: serving never pays scikit-learn's import

        x = np.asarray(x, np.float32)
        dim = min(dim, len(x) - 1, x.shape[1])
        pca = PCA(n_components=dim, svd_solver="randomized" if dim < min(x.shape) // 2 else "full", random_state=seed)
        pca.fit(x)
        manifest = {
            "dim": dim,
            "n_train": len(x),
            "input_dim": x.shape[1],
            "data_hash": data_hash(x),
            "explained_variance_ratio": float(pca.explained_variance_ratio_.sum()),
        }
        return cls(pca.mean_, pca.components_, pca.explained_variance_, power, manifest)

    def transform(self, x: np.ndarray) -> np.ndarray:
        """(N, D) or (D,) -> whitened, L2-normalised (N, dim) or (dim,)."""
        return l2_normalize((np.asarray(x, np.float32) - self.mean) @ self._projection)

    def save(self, directory: Path, name: str = "pca") -> None:
        save_artifact(
            directory,
            name,
            PCA_KIND,
            PCA_VERSION,
            {"power": self.power},
            {"mean": self.mean, "components": self.components, "variances": self.variances},
            {"fit": self.manifest},
        )

    @classmethod
    def load(cls, directory: Path, name: str = "pca") -> PcaWhitening:
        manifest, a = load_artifact(directory, name, PCA_KIND, PCA_VERSION)
        return cls(a["mean"], a["components"], a["variances"], manifest["params"]["power"], manifest.get("fit"))
