"""The live index on a real server: an upload writes no snapshot and rebuilds nothing, a second process
catches up on adds and deletes, a restart replays the log over the snapshot, a damaged snapshot is rebuilt,
loading retries, storage failures are 503s that leave the connection usable and recover, verification
never fails a request, and a reference whose image is gone says so."""

import json
import re
import resource
import shutil
import time

import pytest

from app.manifests import read_manifest
from tests.api.conftest import CONFIG, Server, wait_job
from tests.conftest import PENN

KEY = "live-key"
H = {"X-API-Key": KEY}


def metric(server, name: str) -> float:
    text = server.client.get("/metrics").text
    m = re.search(rf"^{name} ([0-9.e+-]+)$", text, re.M)
    assert m, f"{name} not in /metrics"
    return float(m.group(1))


def _snapshot_version(data) -> int:
    try:
        return json.loads((data / "index.json").read_text())["version"]
    except (FileNotFoundError, ValueError):
        return -1  # not written yet (or being replaced)


def _upload(client, rows):
    files = [("image", (r.image.name, r.image.read_bytes(), "image/jpeg")) for r in rows]
    meta = [{"lat": r.lat, "lon": r.lon, "label": r.image.name} for r in rows]
    r = client.post("/references", files=files, data={"metadata": json.dumps(meta)}, headers=H)
    assert r.status_code == 202, r.text
    return r.json()


def _locate(client, path, **data):
    r = client.post("/locate", files=[("image", ("q.jpg", path.read_bytes(), "image/jpeg"))], data=data)
    assert r.status_code == 200, r.text
    return r.json()


@pytest.fixture(scope="module")
def rows(mini_manifest):
    return [r for r in read_manifest(mini_manifest) if r.split == "db"]


def test_incremental_updates_across_processes_and_restarts(tmp_path, fitted_models, rows):
    data = tmp_path / "data"
    policy = {"GEOLOC_SNAPSHOT_EVERY_CHANGES": "10"}
    with Server(data, fitted_models, api_key=KEY, extra_env=policy) as a:
        before = metric(a, "geoloc_snapshot_writes")
        wait_job(a.client, _upload(a.client, rows[:12])["job_id"])
        # >= 10 changes pending: the writer takes a snapshot at its next check (slow under a loaded machine).
        # Its file is written before the writer counts it: wait for both, so the count read below is final.
        deadline = time.time() + 180
        while (_snapshot_version(data) < 8 or metric(a, "geoloc_snapshot_writes") <= before) and time.time() < deadline:
            time.sleep(0.3)
        assert _snapshot_version(data) >= 8, "the writer took no snapshot of the uploads"
        writes, rebuilds = metric(a, "geoloc_snapshot_writes"), metric(a, "geoloc_index_full_rebuilds")
        faiss_files = sorted(p.name for p in data.glob("*.faiss"))
        with Server(data, fitted_models, api_key=KEY, worker="none") as b:
            size_b = b.client.get("/ready").json()["index_size"]
            # An upload through A: indexed by A's worker, seen by B at its next request, no snapshot anywhere.
            acc = _upload(a.client, rows[12:13])
            assert wait_job(a.client, acc["job_id"])["status"] == "done"
            assert b.client.get("/ready").json()["index_size"] == size_b + 1
            new_id = acc["reference_ids"][0]
            top = _locate(b.client, rows[12].image, top_k=3)["candidates"][0]
            assert top["reference_id"] == new_id
            assert metric(a, "geoloc_snapshot_writes") == writes and metric(a, "geoloc_index_full_rebuilds") == rebuilds
            assert metric(b, "geoloc_index_full_rebuilds") == 0  # it loaded A's snapshot, and caught up since
            assert sorted(p.name for p in data.glob("*.faiss")) == faiss_files
            # A deletion through A is gone from B's next search.
            assert a.client.delete(f"/references/{new_id}", headers=H).status_code == 200
            after = _locate(b.client, rows[12].image, top_k=10)
            assert new_id not in [c["reference_id"] for c in after["candidates"]]
            assert metric(b, "geoloc_index_tombstones") == 1
        # Killed (no clean stop): the restart replays the log over the last snapshot.
        version = a.client.get("/ready").json()["version"]
        snapshot_version = _snapshot_version(data)
        assert 8 <= snapshot_version <= version - 2  # written by the policy, not for the upload or the delete
        a.kill()
    with Server(data, fitted_models, api_key=KEY) as again:
        ready = again.client.get("/ready").json()
        assert ready["version"] == version and ready["index_size"] == 12
        assert metric(again, "geoloc_index_full_rebuilds") == 0
        assert metric(again, "geoloc_index_replayed_at_start") == version - snapshot_version  # only what came after
    # A clean stop wrote a final snapshot; truncate its manifest: the next start rebuilds, never a 503.
    manifest = data / "index.json"
    manifest.write_text(manifest.read_text()[:40])
    with Server(data, fitted_models, api_key=KEY) as damaged:
        assert damaged.client.get("/ready").json()["index_size"] == 12
        assert metric(damaged, "geoloc_index_full_rebuilds") == 1
        top = _locate(damaged.client, rows[3].image, top_k=1)["candidates"][0]
        assert top["label"] == rows[3].image.name


def test_loading_retries_until_the_pipeline_appears(tmp_path, fitted_models):
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(fitted_models / "squeezenet1_1.onnx", models / "squeezenet1_1.onnx")
    s = Server(tmp_path / "data", models, api_key=KEY)
    try:
        deadline = time.time() + 60
        body = {}
        while time.time() < deadline:
            try:
                r = s.client.get("/ready")
                body = r.json()
                if "retrying" in body.get("message", ""):
                    break
            except Exception:
                pass
            time.sleep(0.3)
        assert r.status_code == 503 and body["error"] == "not_ready" and "geoloc fit" in body["message"]
        shutil.copytree(fitted_models / "pipelines", models / "pipelines")
        assert s.wait_ready(timeout=90)["config"] == CONFIG  # no restart
    finally:
        s.stop()


def test_storage_failures_are_503s_that_recover_without_a_restart(tmp_path, fitted_models, rows):
    data = tmp_path / "data"
    with Server(data, fitted_models, api_key=KEY) as s:
        wait_job(s.client, _upload(s.client, rows[:2])["job_id"])
        images = data / "images"
        images.rename(tmp_path / "images.moved")
        images.write_bytes(b"a file where the images folder should be")
        r = s.client.post(
            "/references",
            files=[("image", ("x.jpg", rows[2].image.read_bytes(), "image/jpeg"))],
            data={"lat": rows[2].lat, "lon": rows[2].lon},
            headers=H,
        )
        assert r.status_code == 503 and r.json()["error"] == "storage_unavailable", r.text
        assert s.client.get("/health").status_code == 200  # the same keep-alive connection still works
        images.unlink()
        (tmp_path / "images.moved").rename(images)
        assert s.client.get("/references").json()["total"] == 2  # nothing lost
        # A full disk for the server process (RLIMIT_FSIZE on its pid), then space again.
        photo = PENN / "photos" / "img_00002.jpg"  # under 1 MB: the upload stays in memory, only the data dir is full
        soft, hard = resource.prlimit(s.proc.pid, resource.RLIMIT_FSIZE)
        resource.prlimit(s.proc.pid, resource.RLIMIT_FSIZE, (100_000, hard))
        try:
            r = s.client.post(
                "/references",
                files=[("image", ("p.jpg", photo.read_bytes(), "image/jpeg"))],
                data={"lat": 39.95, "lon": -75.19},
                headers=H,
            )
            assert r.status_code == 503 and r.json()["error"] == "storage_unavailable", r.text
        finally:
            resource.prlimit(s.proc.pid, resource.RLIMIT_FSIZE, (soft, hard))
        acc = _upload(s.client, rows[2:3])
        assert wait_job(s.client, acc["job_id"])["status"] == "done"
        assert s.client.get("/references").json()["total"] == 3


def test_rerank_on_real_photos_and_a_missing_image(tmp_path, fitted_models, rows):
    with Server(tmp_path / "data", fitted_models, api_key=KEY) as s:
        acc = _upload(s.client, rows)
        wait_job(s.client, acc["job_id"])
        queries = sorted((PENN / "photos").glob("*.jpg"))[20:26]
        for q in queries:  # OpenCV's USAC raises on degenerate pairs: never a 500
            res = _locate(s.client, q, top_k=5, rerank="true")
            assert "rerank" in res["timings_ms"] and all("inliers" in c for c in res["candidates"])
        ref = acc["reference_ids"][0]
        sha = s.client.get(f"/references/{ref}").json()["sha256"]
        next((tmp_path / "data" / "images").glob(f"{sha}.*")).unlink()
        assert s.client.get(f"/references/{ref}").status_code == 200
        r = s.client.get(f"/references/{ref}/image")
        assert r.status_code == 404 and r.json()["error"] == "image_missing"
        assert "exists" in r.json()["message"]
