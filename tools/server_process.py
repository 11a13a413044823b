"""``geoloc serve`` as a child process on a free loopback port.

The end-to-end tests and the benchmarks both need a real uvicorn server they can start, wait for, kill
and restart; one helper keeps them measuring and testing the same thing users run."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """stop() is SIGTERM (then SIGKILL after 30 s), kill() is SIGKILL; the log goes beside the data dir.

    Auth is on, as for users: with ``api_key`` the server gets it in GEOLOC_API_KEY and the caller sends it
    where it means to; without one the server makes DATA_DIR/api_key, and once it is ready ``api_key`` holds
    that key and ``client`` sends it on every request (callers that are not about auth need not care).
    ``no_auth`` starts it with --no-auth; ``code`` runs the ``app`` package of another tree (a checkout or a
    ``git archive`` of an older commit) instead of this one's."""

    def __init__(
        self,
        data_dir: Path,
        models_dir: Path,
        config: str,
        *,
        api_key: str | None = None,
        worker: str = "inprocess",
        extra_env: dict | None = None,
        no_auth: bool = False,
        code: Path | None = None,
    ):
        self.data_dir, self.models_dir, self.config = data_dir, models_dir, config
        self.api_key, self._key_from_file = api_key, not api_key and not no_auth
        data_dir.parent.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        inherited = {k: v for k, v in os.environ.items() if k not in ("GEOLOC_API_KEY", "GEOLOC_NO_AUTH")}
        env = {**inherited, "PYTHONUNBUFFERED": "1", **(extra_env or {})}
        if code is not None:  # another tree's ``app`` (an older commit, for a benchmark's baseline)
            env["PYTHONPATH"] = str(code)
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
                config,
                "--worker",
                worker,
                *(["--no-auth"] if no_auth else []),
            ],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=code,  # ``python -m`` puts the working directory first on sys.path
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
                    if self._key_from_file:
                        from app.apikey import key_path, read_key

                        self.api_key = read_key(key_path(self.data_dir))
                        self.client.headers["X-API-Key"] = self.api_key
                    return r.json()
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise TimeoutError(f"server not ready: {self.read_log()}")

    def __enter__(self) -> ServerProcess:
        """``with ServerProcess(...) as s``: started, ready, and stopped on the way out."""
        try:
            self.wait_ready()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def read_log(self) -> str:
        self.log.flush()
        return Path(self.log.name).read_text()[-3000:]

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

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


def wait_job(client: httpx.Client, job_id: str, timeout: float = 180) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["status"] in ("done", "failed"):
            return job
        time.sleep(0.2)
    raise TimeoutError(f"job {job_id} still {job}")
