"""The thesis-style baseline against our pipelines, in one run, through ``geoloc eval``'s ``evaluate``.

The baseline is what the thesis improves on: RootSIFT, a Lloyd k-means codebook, plain VLAD at full
dimension (64 x 128 = 8,192 floats), exhaustive float search (configuration ``sift-vlad-kmeans``).
Extraction runs on one thread here (``workers=1``) so the per-stage times are not inflated by a pool.
Configurations that extract the same features share them through a cache in a temporary directory.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable
from pathlib import Path

from app.engine.configs import DEFAULT_CONFIG, get_config
from app.evaluation.evaluate import evaluate

BASELINE = "sift-vlad-kmeans"
COMPARED = (BASELINE, "sift-mbvlad", DEFAULT_CONFIG, "hybrid-bin")


def run(
    manifest: Path, models_dir: Path, folds: int = 5, configs: Iterable[str] = COMPARED, progress=print
) -> list[dict]:
    out = []
    with tempfile.TemporaryDirectory(prefix="geoloc-bench-cache-") as cache:
        for name in configs:
            progress(f"baseline comparison: evaluating {name} ({folds} folds)")
            result = evaluate(
                manifest, get_config(name), folds=folds, workers=1, cache_dir=Path(cache), models_dir=models_dir
            )
            out.append(result.model_dump(exclude={"queries"}))
    return out
