"""hybrid-bin fitted by `geoloc fit` on 40 penn captures (120 photos and crops), once for the run.

Two modules need this very fit: tests/test_fit_reproducible.py compares it with a fit made on two threads,
and tests/api/test_own_calibration.py serves it as a collection's own calibration. A fit of this size is
one of the suite's dearest steps, so it is made once, shared by the xdist workers (``built_once``), on one
thread everywhere (BLAS, OpenMP, onnxruntime) and with ``GEOLOC_MAX_RADIUS_M=90`` (the widest disc that
counts as an estimate, read by the fit). A plugin of the root conftest (``pytest_plugins``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import PENN, built_once

CONFIG = "hybrid-bin"
THREADS_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "GEOLOC_ORT_THREADS")
#: Read by the fit: the widest disc that counts as an estimate.
MAX_RADIUS_M = "90"


def forty_manifest(directory: Path, penn_index: list[dict]) -> tuple[Path, Path]:
    """40 captures (a photo and two crops each) as db rows, and the next capture's photo as a query."""
    from app.manifests import Row, write_manifest

    captures = [r for r in penn_index if r["photo"]]
    rows = []
    for r in captures[:40]:
        for img in [r["photo"]] + r["crops"].split(";")[:2]:
            rows.append(Row((PENN / img).resolve(), float(r["lat"]), float(r["lon"]), "db", r["photo_id"]))
    path = directory / "forty.csv"
    write_manifest(path, rows)
    return path, (PENN / captures[40]["photo"]).resolve()


def linked_models(models: Path, models_dir: Path) -> Path:
    """A models dir of its own whose model files are links to the session's."""
    models.mkdir()
    for f in models_dir.iterdir():
        if f.is_file():
            (models / f.name).symlink_to(f)
    return models


def fit_forty(manifest: Path, models: Path, threads: int) -> str:
    """`geoloc fit` of ``CONFIG`` with every thread setting at ``threads``; its stdout."""
    env = {**os.environ, "GEOLOC_MAX_RADIUS_M": MAX_RADIUS_M, **{k: str(threads) for k in THREADS_ENV}}
    args = ["fit", "--manifest", str(manifest), "--config", CONFIG, "--models-dir", str(models)]
    out = subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=900, env=env)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out.stdout


@pytest.fixture(scope="session")
def forty_fitted(tmp_path_factory, models_dir, penn_index) -> tuple[Path, Path, Path]:
    """(models dir, manifest, query photo): the one-thread fit, made once for the run. Never written: copy
    the models dir to change it."""

    def build(root: Path) -> None:
        manifest, _ = forty_manifest(root, penn_index)
        fit_forty(manifest, linked_models(root / "models", models_dir), threads=1)

    root = built_once(tmp_path_factory, "forty", build)
    manifest, query = forty_manifest(tmp_path_factory.mktemp("forty-manifest"), penn_index)
    return root / "models", manifest, query
