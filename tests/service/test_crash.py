"""A worker killed (SIGKILL) in the middle of an ingestion loses nothing and duplicates nothing."""

import json
import signal
import time

from tests.conftest import PENN
from tests.service.conftest import Server, start_worker, wait_job

N = 50


def test_worker_killed_during_ingestion(tmp_path, fitted_models, penn_index):
    crops = [c for r in penn_index for c in r["crops"].split(";")][:N]
    positions = {c: (float(r["lat"]), float(r["lon"])) for r in penn_index for c in r["crops"].split(";")}
    data = tmp_path / "data"
    server = Server(data, fitted_models, worker="none")
    worker = None
    try:
        server.wait_ready()
        c = server.client
        files = [("image", (c_.split("/")[-1], (PENN / c_).read_bytes(), "image/jpeg")) for c_ in crops]
        meta = [{"lat": positions[c_][0], "lon": positions[c_][1], "label": c_} for c_ in crops]
        r = c.post("/references", files=files, data={"metadata": json.dumps(meta)})
        assert r.status_code == 202, r.text
        job_id, ids = r.json()["job_id"], r.json()["reference_ids"]
        assert len(set(ids)) == N

        worker = start_worker(data, fitted_models, tmp_path / "worker.log")
        deadline = time.time() + 120
        while c.get(f"/jobs/{job_id}").json()["indexed"] < 8 and time.time() < deadline:
            time.sleep(0.05)
        worker.send_signal(signal.SIGKILL)
        worker.wait()
        partial = c.get(f"/jobs/{job_id}").json()
        assert 8 <= partial["indexed"] < N, partial  # killed mid-way

        worker = start_worker(data, fitted_models, tmp_path / "worker.log")
        job = wait_job(c, job_id)
        assert job["status"] == "done" and job["indexed"] == N and job["failed"] == 0
        assert c.get("/references", params={"limit": 500}).json()["total"] == N
        deadline = time.time() + 30
        while c.get("/ready").json()["index_size"] != N and time.time() < deadline:
            time.sleep(0.2)
        assert c.get("/ready").json()["index_size"] == N

        for ref_id, crop in zip(ids, crops, strict=True):  # every reference is found with its own image
            res = c.post("/locate", files=[("image", ("q.jpg", (PENN / crop).read_bytes()))], data={"top_k": 1})
            assert res.json()["candidates"][0]["reference_id"] == ref_id, crop
    finally:
        if worker is not None and worker.poll() is None:
            worker.kill()
        server.stop()
