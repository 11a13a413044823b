"""Crash safety: SIGKILL the worker, or the API process, at random moments during an ingestion.

Afterwards every accepted reference exists exactly once, the index size equals the metadata count, and
each reference is found first by a query with its own image. `make test` uses 100 of the 224 px crops
(GEOLOC_CRASH_N sets another count); `make crash-full` runs the same with 200 photos of 1600 px."""

import io
import json
import os
import random
import signal
import time

import httpx
import pytest
from PIL import Image

from tests.api.conftest import Server, start_worker, wait_job
from tests.conftest import PENN

#: Not in `make test-quick`. Each test runs on SQLite and on PostgreSQL (the ``backend`` fixture: the servers
#: and workers started here inherit its GEOLOC_DATABASE_URL), on PostgreSQL with half of the images (the same
#: kills, in half the time: `make test` stays within its budget).
pytestmark = pytest.mark.crash

FULL = os.environ.get("GEOLOC_CRASH_FULL") == "1"
N = int(os.environ.get("GEOLOC_CRASH_N", "200" if FULL else "100"))
#: The images of one run on each engine.
SHARE = {"sqlite": 1, "postgres": 2}


@pytest.fixture(scope="module")
def images(penn_index) -> list[tuple[str, bytes, float, float]]:
    """N distinct images with positions: crops (CI) or 1600 px photos and re-framed copies (full)."""
    out = []
    if FULL:
        photos = [(r, (PENN / r["photo"]).read_bytes()) for r in penn_index if r["photo"]]
        variant = 0
        while len(out) < N:
            for r, data in photos:
                if len(out) >= N:
                    break
                img = Image.open(io.BytesIO(data)).convert("RGB")
                if variant:  # a slightly different framing: distinct bytes, same place
                    w, h = img.size
                    img = img.crop((variant * 8, variant * 8, w - variant * 8, h - variant * 8))
                buf = io.BytesIO()
                img.save(buf, "JPEG", quality=90)
                out.append((f"{r['photo_id']}_{variant}.jpg", buf.getvalue(), float(r["lat"]), float(r["lon"])))
            variant += 1
    else:
        for r in penn_index:
            for c in r["crops"].split(";"):
                out.append((c.split("/")[-1], (PENN / c).read_bytes(), float(r["lat"]), float(r["lon"])))
        out = out[:N]
    assert len({d for _, d, _, _ in out}) == N
    return out


def _upload(client: httpx.Client, batch) -> dict:
    files = [("image", (name, data, "image/jpeg")) for name, data, _, _ in batch]
    meta = [{"lat": la, "lon": lo, "label": name} for name, _, la, lo in batch]
    r = client.post("/references", files=files, data={"metadata": json.dumps(meta)})
    assert r.status_code == 202, r.text
    return r.json()


def _verify(server: Server, images) -> None:
    c = server.client
    n = len(images)
    listing = c.get("/references", params={"limit": 500}).json()
    assert listing["total"] == n
    assert sorted(i["label"] for i in listing["items"]) == sorted(name for name, _, _, _ in images)
    assert all(i["status"] == "indexed" for i in listing["items"])
    deadline = time.time() + 60
    while c.get("/ready").json()["index_size"] != n and time.time() < deadline:
        time.sleep(0.2)
    assert c.get("/ready").json()["index_size"] == n
    by_label = {i["label"]: i["id"] for i in listing["items"]}
    for name, data, _, _ in images:
        res = c.post("/locate", files=[("image", ("q.jpg", data))], data={"top_k": 1}).json()
        assert res["candidates"][0]["reference_id"] == by_label[name], name


def test_worker_killed_at_random_moments(tmp_path, fitted_models, images, backend):
    images = images[: N // SHARE[backend]]
    data = tmp_path / "data"
    server = Server(data, fitted_models, worker="none")
    worker = None
    rng = random.Random(1)
    try:
        server.wait_ready()
        jobs = [_upload(server.client, images[i : i + 25])["job_id"] for i in range(0, len(images), 25)]
        kills = 0
        worker = start_worker(data, fitted_models, tmp_path / "worker.log")
        while kills < 3:
            time.sleep(rng.uniform(0.5, 3.0))
            pending = server.client.get("/metrics").text
            worker.send_signal(signal.SIGKILL)
            worker.wait()
            kills += 1
            worker = start_worker(data, fitted_models, tmp_path / "worker.log")
            if "geoloc_queue_depth 0.0" in pending:
                break
        for job in jobs:
            assert wait_job(server.client, job, timeout=600)["status"] == "done"
        _verify(server, images)
    finally:
        if worker is not None and worker.poll() is None:
            worker.kill()
        server.stop()


def test_api_killed_at_random_moments(tmp_path, fitted_models, images, backend):
    """The client retries what was not acknowledged; identical bytes are stored once whatever happens."""
    images = images[: N // SHARE[backend]]
    data = tmp_path / "data"
    rng = random.Random(2)
    server = Server(data, fitted_models)
    server.wait_ready()
    batches = [images[i : i + 10] for i in range(0, len(images), 10)]
    kill_at = sorted(rng.sample(range(1, len(batches)), 3))
    try:
        for n, batch in enumerate(batches):
            if n in kill_at:
                time.sleep(rng.uniform(0.0, 1.5))  # somewhere inside the encoding of earlier batches
                server.proc.send_signal(signal.SIGKILL)
                server.proc.wait()
                server.stop()
                server = Server(data, fitted_models)
                server.wait_ready()
            _upload(server.client, batch)
        deadline = time.time() + 600
        while server.client.get("/metrics").text.count("geoloc_queue_depth 0.0") == 0 and time.time() < deadline:
            time.sleep(0.3)
        _verify(server, images)
    finally:
        server.stop()
