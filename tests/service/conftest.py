"""A real uvicorn server on a free port, on a data dir of its own, driven over HTTP with httpx."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from app.datasets import read_manifest

CONFIG = "hybrid-bin"


@pytest.fixture(scope="session")
def fitted_models(models_dir, mini_manifest, squeezenet) -> Path:
    """The session's models dir with hybrid-bin fitted on the mini manifest's db and train rows."""
    from app.engine.configs import get_config
    from app.engine.imageio import load_image
    from app.engine.pipeline import Pipeline, pipeline_dir

    rows = [r for r in read_manifest(mini_manifest) if r.split in ("db", "train")]
    pipe = Pipeline(get_config(CONFIG), cnn=squeezenet)
    pipe.fit([pipe.extract(load_image(r.image.read_bytes()).rgb) for r in rows])
    pipe.save(pipeline_dir(models_dir, CONFIG))
    return models_dir


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``geoloc serve`` (or ``geoloc worker``) as a child process; stop() is SIGTERM, kill() is SIGKILL."""

    def __init__(
        self,
        data_dir: Path,
        models_dir: Path,
        *,
        api_key: str | None = None,
        worker: str = "inprocess",
        extra_env: dict | None = None,
    ):
        self.data_dir, self.models_dir = data_dir, models_dir
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "GEOLOC_ORT_THREADS": "1", **(extra_env or {})}
        if api_key:
            env["GEOLOC_API_KEY"] = api_key
        self.log = open(data_dir.parent / f"server-{self.port}.log", "w")  # noqa: SIM115
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "app.cli",
                "serve",
                "--port",
                str(self.port),
                "--data-dir",
                str(data_dir),
                "--models-dir",
                str(models_dir),
                "--config",
                CONFIG,
                "--worker",
                worker,
            ],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            env=env,
        )
        self.client = httpx.Client(base_url=self.url, timeout=60)

    def wait_ready(self, timeout: float = 120) -> dict:
        deadline = time.time() + timeout
        while time.time() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}: {self.read_log()}")
            try:
                r = self.client.get("/ready")
                if r.status_code == 200:
                    return r.json()
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise TimeoutError(f"server not ready: {self.read_log()}")

    def read_log(self) -> str:
        self.log.flush()
        return Path(self.log.name).read_text()[-3000:]

    def stop(self) -> None:
        self.client.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


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


def wait_job(client: httpx.Client, job_id: str, timeout: float = 180) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["status"] in ("done", "failed"):
            return job
        time.sleep(0.2)
    raise TimeoutError(f"job {job_id} still {job}")
