"""A real uvicorn server on a free port, on a data dir of its own, driven over HTTP with httpx."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from app.manifests import read_manifest
from tools.server_process import ServerProcess, wait_job  # noqa: F401  (re-exported for the tests)

CONFIG = "hybrid-bin"


@pytest.fixture(scope="session")
def fitted_models(models_dir, mini_manifest, squeezenet) -> Path:
    """The session's models dir with hybrid-bin fitted on the mini manifest's db and train rows."""
    from app.engine.configs import get_config
    from app.engine.imageio import load_image
    from app.engine.pipeline import Pipeline, pipeline_dir

    rows = [r for r in read_manifest(mini_manifest) if r.split in ("db", "train")]
    pipe = Pipeline(get_config(CONFIG), global_model=squeezenet)
    pipe.fit([pipe.extract(load_image(r.image.read_bytes()).rgb) for r in rows])
    pipe.save(pipeline_dir(models_dir, CONFIG))
    return models_dir


@pytest.fixture(scope="session")
def mini_collection(tmp_path_factory, fitted_models, mini_manifest) -> Path:
    """A data dir holding the mini manifest's 30 db images, ingested once per session by `geoloc ingest`.
    Tests read it or copy it; none may change its references."""
    data = tmp_path_factory.mktemp("collection") / "data"
    args = ["ingest", "--manifest", str(mini_manifest), "--split", "db", "--config", CONFIG]
    out = subprocess.run(
        [sys.executable, "-m", "app.cli", *args, "--data-dir", str(data), "--models-dir", str(fitted_models)],
        capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    assert "ingested 30 new references" in out.stdout, out.stdout + out.stderr
    return data


class Server(ServerProcess):
    """The tests' server: the fitted hybrid-bin models, one onnxruntime thread."""

    def __init__(self, data_dir: Path, models_dir: Path, *, extra_env: dict | None = None, **kwargs):
        super().__init__(
            data_dir, models_dir, CONFIG, extra_env={"GEOLOC_ORT_THREADS": "1", **(extra_env or {})}, **kwargs
        )


def start_worker(data_dir: Path, models_dir: Path, log: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "app.cli",
            "worker",
            "--data-dir",
            str(data_dir),
            "--models-dir",
            str(models_dir),
            "--config",
            CONFIG,
            "--batch",
            "4",
        ],
        stdout=open(log, "a"),
        stderr=subprocess.STDOUT,  # noqa: SIM115
        env={**os.environ, "PYTHONUNBUFFERED": "1", "GEOLOC_ORT_THREADS": "1"},
    )
