"""Worker failover: when the process that holds a data dir's worker lock dies, an API server on the same
data dir that was started with an in-process worker takes the lock over and indexes the queued uploads,
with nobody restarting anything by hand."""

from __future__ import annotations

import json
import shutil
import signal
import time
from pathlib import Path

import httpx

from tests.api.conftest import Server, start_worker
from tests.conftest import PENN

#: How long an upload may stay queued once the lock holder is gone (the retry runs every 1 s here).
TAKEOVER_S = 30.0
#: A 224 px crop the mini collection does not hold (its captures are the penn index's first 16).
NEW_PHOTO = PENN / "crops" / "img_00040_0.jpg"


def copy_collection(src: Path, dest: Path) -> Path:
    shutil.copytree(src, dest, ignore=shutil.ignore_patterns("worker.lock"))
    return dest


def upload(server: Server) -> str:
    r = server.client.post(
        "/references",
        files=[("image", (NEW_PHOTO.name, NEW_PHOTO.read_bytes(), "image/jpeg"))],
        data={"metadata": json.dumps([{"lat": 39.95, "lon": -75.19}])},
    )
    assert r.status_code == 202, r.text
    return r.json()["job_id"]


def wait_done(client: httpx.Client, job_id: str, timeout: float) -> dict:
    """The job once it is done or failed, or its last state after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    job = client.get(f"/jobs/{job_id}").json()
    while job["status"] not in ("done", "failed") and time.monotonic() < deadline:
        time.sleep(0.25)
        job = client.get(f"/jobs/{job_id}").json()
    return job


def assert_takes_over(b: Server) -> None:
    """B, which had no worker, indexes an upload within the bound and says its worker is now in-process."""
    job_id = upload(b)
    t0 = time.monotonic()
    job = wait_done(b.client, job_id, TAKEOVER_S)
    assert job["status"] == "done", f"still {job} after {TAKEOVER_S} s:\n{b.read_log()}"
    assert time.monotonic() - t0 < TAKEOVER_S
    ready = b.client.get("/ready").json()
    assert ready["worker"] == "in-process", ready
    assert "took over the worker lock" in b.read_log()


def stop_cleanly(b: Server) -> None:
    """SIGTERM stops the taken-over worker and snapshot writer: the writer's last snapshot holds the upload
    (31 references), the shutdown completes, nothing raised on the way."""
    b.stop()
    log = Path(b.log.name).read_text()
    assert "(31 references)" in log and "Application shutdown complete" in log, log[-3000:]
    assert "Traceback" not in log, log[-3000:]


def test_api_server_takes_over_from_a_killed_api_server(tmp_path, fitted_models, mini_collection):
    data = copy_collection(mini_collection, tmp_path / "data")
    env = {"GEOLOC_WORKER_RETRY_SECONDS": "1"}
    a = Server(data, fitted_models, extra_env=env)
    b = None
    try:
        assert a.wait_ready()["worker"] == "in-process"
        b = Server(data, fitted_models, extra_env=env)
        assert b.wait_ready()["worker"] == "external"  # A holds the lock
        a.kill()
        assert_takes_over(b)
        stop_cleanly(b)
    finally:
        a.stop()
        if b is not None:
            b.stop()


def test_api_server_takes_over_from_a_killed_geoloc_worker(tmp_path, fitted_models, mini_collection):
    data = copy_collection(mini_collection, tmp_path / "data")
    log = tmp_path / "worker.log"
    worker = start_worker(data, fitted_models, log)
    b = None
    try:
        deadline = time.monotonic() + 120
        while "worker: " not in log.read_text() and time.monotonic() < deadline:  # it holds the lock by now
            assert worker.poll() is None, log.read_text()
            time.sleep(0.2)
        b = Server(data, fitted_models, extra_env={"GEOLOC_WORKER_RETRY_SECONDS": "1"})
        assert b.wait_ready()["worker"] == "external"
        worker.send_signal(signal.SIGKILL)
        worker.wait()
        assert_takes_over(b)
        stop_cleanly(b)
    finally:
        if worker.poll() is None:
            worker.kill()
            worker.wait()
        if b is not None:
            b.stop()
