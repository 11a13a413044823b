"""Codes for the index-scale benchmark: penn-campus-gps's real codes and synthetic codes shaped like them.

Why synthetic: encoding 10^7 photos at 5 images/s would take weeks, and the index's cost and accuracy depend
only on the codes' shape. The generator is a Gaussian fitted to the real penn reference codes (their mean
and covariance, so the synthetic codes have the real spectrum after whitening), then L2-normalised as the
pipeline's codes are. Real penn codes are placed first (ids 0..n_penn-1) so that every collection size holds
them, and its real queries have their true matches among 10^5-10^7 synthetic distractors.

Everything lives on disk under ``out/``: the codes as one float16 memory-mapped file (the collection's
"store"; the index's exact re-rank reads it by id), written in chunks so that no copy of 10^7 codes is held
in RAM. float16 halves the file (5 GB at 10^7); the values stored *are* the collection's codes, and the exact
search is computed on them too, so no precision is lost between the exact and the approximate side.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import faiss
import numpy as np

CHUNK = 100_000


@dataclass
class PennCodes:
    """Real float codes of penn-campus-gps: its db references and its query images."""

    refs: np.ndarray  # (n_refs, dim) float32, unit rows
    queries: np.ndarray  # (n_queries, dim) float32, unit rows

    def save(self, path: Path) -> None:
        np.savez(path, refs=self.refs, queries=self.queries)

    @classmethod
    def load(cls, path: Path) -> PennCodes:
        z = np.load(path)
        return cls(z["refs"].astype(np.float32), z["queries"].astype(np.float32))


def encode_penn(manifest: Path, models_dir: Path, config: str) -> PennCodes:
    """Encode the manifest's db rows as references and its query rows as queries (the SVM bank's selection
    for queries, as evaluation and /locate do), with the fitted pipeline. Slow (minutes): cache the result."""
    from app.engine.pipeline import load_pipeline
    from app.manifests import read_manifest

    pipe = load_pipeline(models_dir, config)
    rows = read_manifest(manifest)
    refs, queries = [], []
    for row in rows:
        if row.split not in ("db", "query"):
            continue
        f = pipe.extract(pipe.decode(row.image.read_bytes()).rgb)
        if row.split == "db":
            refs.append(pipe.encode_features(f).float_)
        else:
            queries.append(pipe.encode_features(f, pipe.select(f)).float_)
    return PennCodes(np.stack(refs).astype(np.float32), np.stack(queries).astype(np.float32))


def penn_positions(manifest: Path) -> tuple[np.ndarray, np.ndarray]:
    """(lat, lon) of the manifest's db rows and query rows, in the order ``encode_penn`` encodes them."""
    from app.manifests import read_manifest

    rows = read_manifest(manifest)
    pick = lambda split: np.array([(r.lat, r.lon) for r in rows if r.split == split], np.float64)  # noqa: E731
    return pick("db"), pick("query")


def unit_rows(x: np.ndarray) -> np.ndarray:
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


@dataclass
class CodeGenerator:
    """x = normalise(mean + z @ basis), z ~ N(0, I): a Gaussian with the real codes' mean and covariance."""

    mean: np.ndarray  # (dim,)
    basis: np.ndarray  # (dim, dim): eigenvectors scaled by the square roots of the eigenvalues

    @classmethod
    def fit(cls, real: np.ndarray, floor: float = 1e-3) -> CodeGenerator:
        """Fit on real codes. With fewer codes than dimensions' worth of samples the smallest eigenvalues are
        noise (or zero): they are floored at ``floor`` times the mean eigenvalue, so every direction varies."""
        mean = real.mean(axis=0)
        cov = np.cov(real - mean, rowvar=False)
        w, v = np.linalg.eigh(cov)
        w = np.maximum(w, floor * w.mean())
        return cls(mean.astype(np.float32), (v * np.sqrt(w)).T.astype(np.float32))

    @property
    def dim(self) -> int:
        return len(self.mean)

    def spectrum(self) -> np.ndarray:
        """Eigenvalues, largest first (what the docs report about the generator)."""
        return np.sort((self.basis**2).sum(axis=1))[::-1]

    def draw(self, n: int, rng: np.random.Generator) -> np.ndarray:
        z = rng.standard_normal((n, self.dim), dtype=np.float32)
        return unit_rows(self.mean + z @ self.basis)

    def noisy_copies(self, src: np.ndarray, cosine: float, rng: np.random.Generator) -> np.ndarray:
        """Queries: each source plus a fresh draw of the same distribution (mean removed), scaled so the
        query's cosine to its source is about ``cosine`` (the real queries' cosine to their best match)."""
        noise = unit_rows(rng.standard_normal((len(src), self.dim), dtype=np.float32) @ self.basis)
        s = np.sqrt(max(1.0 / cosine**2 - 1.0, 0.0))
        return unit_rows(src + s * noise)


def codes_file(out_dir: Path, n: int, penn: PennCodes, gen: CodeGenerator, seed: int = 0) -> np.memmap:
    """The collection's codes, float16, memory-mapped: penn's real references first, then synthetic ones.
    Chunk ``c`` of the synthetic part is drawn from seed (seed, c), so a file of 10^6 rows is the prefix
    of the one of 10^7; a file of at least ``n`` rows is reused."""
    meta_path = out_dir / "codes.json"
    path = out_dir / "codes.f16"
    dim = gen.dim
    if meta_path.exists() and path.exists():
        meta = json.loads(meta_path.read_text())
        if meta["rows"] >= n and meta["seed"] == seed and meta["n_penn"] == len(penn.refs):
            return np.memmap(path, np.float16, "r", shape=(meta["rows"], dim))
    out_dir.mkdir(parents=True, exist_ok=True)
    mm = np.memmap(path, np.float16, "w+", shape=(n, dim))
    p = len(penn.refs)
    mm[:p] = penn.refs
    for c, lo in enumerate(range(p, n, CHUNK)):
        hi = min(lo + CHUNK, n)
        mm[lo:hi] = gen.draw(hi - lo, np.random.default_rng([seed, c]))
    mm.flush()
    del mm
    meta_path.write_text(json.dumps({"rows": n, "seed": seed, "n_penn": p, "dim": dim}))
    return np.memmap(path, np.float16, "r", shape=(n, dim))


def chunks(codes: np.ndarray, n: int, chunk: int = CHUNK):
    """(first id, float32 rows) of the first ``n`` codes, one chunk in RAM at a time."""
    for lo in range(0, n, chunk):
        yield lo, np.asarray(codes[lo : min(lo + chunk, n)], dtype=np.float32)


def exact_search(codes: np.ndarray, n: int, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact inner-product top-k of ``queries`` among the first ``n`` codes, streamed chunk by chunk."""
    heap = faiss.ResultHeap(len(queries), k, keep_max=True)
    for lo, x in chunks(codes, n):
        d, i = faiss.knn(queries, x, min(k, len(x)), metric=faiss.METRIC_INNER_PRODUCT)
        if d.shape[1] < k:
            pad = k - d.shape[1]
            d = np.hstack([d, np.full((len(d), pad), -np.inf, np.float32)])
            i = np.hstack([i, np.full((len(i), pad), -1, np.int64)])
        heap.add_result(d, np.where(i >= 0, i + lo, -1))
    heap.finalize()
    return heap.D, heap.I


def sign_bits(x: np.ndarray) -> np.ndarray:
    """256-bit sign codes of float codes (the binary configurations' shape)."""
    return np.packbits(x > 0, axis=1)


def effective_dimension(x: np.ndarray) -> float:
    """The participation ratio of the covariance's eigenvalues, (sum l)^2 / sum l^2: how many directions
    the codes really vary in (256 for isotropic 256-d codes, 1 for codes on one line)."""
    eig = np.linalg.eigvalsh(np.cov(x, rowvar=False))
    return float(eig.sum() ** 2 / (eig**2).sum())


def fidelity(penn: PennCodes, gen: CodeGenerator, rng: np.random.Generator, n_synthetic: int = 20_000) -> dict:
    """How far the synthetic distractors are from penn's real queries, against the real references: the
    measure that decides whether an approximate index can find the queries' exact neighbours. Cosine
    percentiles of query-to-reference pairs (real, then synthetic), each query's best real reference (its
    match, mostly) against the best of as many synthetic codes, and the effective dimension of both."""
    synthetic = gen.draw(n_synthetic, rng)
    real = penn.queries @ penn.refs.T
    fake = penn.queries @ synthetic.T
    pct = (50, 90, 99, 99.9)
    refs = penn.refs @ penn.refs.T
    return {
        "query_real_cos_pct": dict(zip(pct, np.percentile(real, pct).round(3).tolist(), strict=True)),
        "query_synthetic_cos_pct": dict(zip(pct, np.percentile(fake, pct).round(3).tolist(), strict=True)),
        "best_real_median": float(np.median(real.max(axis=1))),
        "best_synthetic_same_count_median": float(np.median(fake[:, : len(penn.refs)].max(axis=1))),
        "real_ref_pairs_cos_999": float(np.percentile(refs[~np.eye(len(refs), dtype=bool)], 99.9)),
        "effective_dim_real": effective_dimension(penn.refs),
        "effective_dim_synthetic": effective_dimension(synthetic),
    }
