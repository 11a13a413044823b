"""Search latency and bytes per reference as the collection grows, on synthetic codes of production size.

Penn-campus-gps has a few hundred references; a city's collection has 10^5-10^6. The codes here are
random but shaped like ours (256-d L2-normalised floats after PCA, 256-bit sign codes of the same
vectors), and each query is a noisy copy of one reference, so the exact float search has a right answer
and the binary and two-stage modes can be scored by how often they agree with it. Searches go through
``ReferenceIndex.search``, one query at a time on one FAISS thread, as the service runs them.

The thesis-style baseline (full-dimension VLAD: 64 x 128 = 8,192 floats, exhaustive) is measured the
same way while it fits in memory.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass

import numpy as np

from app.engine.configs import get_config
from app.engine.index.references import ReferenceIndex
from bench.common import median_ms

SIZES = (1_000, 10_000, 100_000, 1_000_000)
DIM, BITS, BASELINE_DIM = 256, 256, 8192
#: Largest baseline collection we build: 100k x 8,192 float32 is 3.3 GB; 1M would be 33 GB (> 24 GB here).
BASELINE_MAX = 100_000


@dataclass
class SearchFigures:
    n: int
    mode: str
    dim: str
    median_ms: float
    bytes_per_ref: float
    agrees_with_float_top1: float | None  # fraction of queries whose top-1 equals the exact float top-1


def _unit_rows(x: np.ndarray) -> np.ndarray:
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


def synthetic_codes(n: int, dim: int, rng: np.random.Generator, chunk: int = 100_000) -> np.ndarray:
    out = np.empty((n, dim), np.float32)
    for s in range(0, n, chunk):
        out[s : s + chunk] = _unit_rows(rng.standard_normal((min(chunk, n - s), dim), dtype=np.float32))
    return out


def noisy_queries(refs: np.ndarray, n_queries: int, rng: np.random.Generator, noise: float = 2.0) -> np.ndarray:
    """Copies of random references plus noise of twice their norm (cosine ~0.45 to their source): far
    enough that among 10^6 random codes a 256-bit Hamming search starts to miss, as real queries do."""
    src = refs[rng.choice(len(refs), n_queries, replace=False)]
    noise_v = rng.standard_normal(src.shape, dtype=np.float32) * (noise / np.sqrt(src.shape[1]))
    return _unit_rows(src + noise_v)


def sign_bits(x: np.ndarray) -> np.ndarray:
    return np.packbits(x > 0, axis=1)


def _time_queries(index: ReferenceIndex, qf, qb, mode: str, k: int = 10) -> tuple[float, np.ndarray]:
    times, top1 = [], []
    for f, b in zip(qf, qb, strict=True):
        t0 = time.perf_counter()
        _, ids = index.search(f, b, k, mode)
        times.append((time.perf_counter() - t0) * 1000)
        top1.append(ids[0] if len(ids) else -1)
    return median_ms(times), np.array(top1)


def measure_ours(n: int, n_queries: int, seed: int = 0) -> list[SearchFigures]:
    rng = np.random.default_rng([seed, n])
    refs = synthetic_codes(n, DIM, rng)
    index = ReferenceIndex(get_config("hybrid-bin"), DIM, BITS)
    index.add(np.arange(n, dtype=np.int64), refs, sign_bits(refs))
    qf = noisy_queries(refs, n_queries, rng)
    qb = sign_bits(qf)
    del refs
    gc.collect()
    float_b = index.float.memory_bytes_per_vector()
    binary_b = index.binary.memory_bytes_per_vector()
    out = []
    exact = None
    for mode in ("float", "binary", "two-stage"):
        ms, top1 = _time_queries(index, qf, qb, mode)
        if mode == "float":
            exact = top1
        out.append(
            SearchFigures(
                n,
                mode,
                f"{DIM} floats" if mode == "float" else f"{BITS} bits" if mode == "binary" else "both",
                ms,
                {"float": float_b, "binary": binary_b, "two-stage": float_b + binary_b}[mode],
                float(np.mean(top1 == exact)),
            )
        )
    return out


def measure_baseline(n: int, n_queries: int, seed: int = 0) -> SearchFigures:
    """The full-dimension exhaustive float search of the thesis-style baseline (sift-vlad-kmeans)."""
    rng = np.random.default_rng([seed, n, 1])
    refs = synthetic_codes(n, BASELINE_DIM, rng)
    index = ReferenceIndex(get_config("sift-vlad-kmeans"), BASELINE_DIM, None)
    index.add(np.arange(n, dtype=np.int64), refs, None)
    qf = noisy_queries(refs, n_queries, rng)
    del refs
    gc.collect()
    ms, _ = _time_queries(index, qf, [None] * len(qf), "float")
    return SearchFigures(
        n, "float (baseline)", f"{BASELINE_DIM} floats", ms, index.float.memory_bytes_per_vector(), None
    )


def run(sizes=SIZES, n_queries: int = 200, baseline_queries: int = 30, progress=print) -> list[SearchFigures]:
    out: list[SearchFigures] = []
    for n in sizes:
        progress(f"search scaling: {n:,} references (256-d floats + 256-bit codes)")
        out += measure_ours(n, n_queries)
        gc.collect()
        if n <= BASELINE_MAX:
            progress(f"search scaling: {n:,} references, baseline {BASELINE_DIM}-d floats")
            out.append(measure_baseline(n, baseline_queries))
            gc.collect()
    return out
