"""Two hosts on one PostgreSQL store and one Milvus collection: two real uvicorn servers with data dirs of
their own, GEOLOC_MILVUS_URI naming the session's Milvus (the ``milvus`` wheel's embedded standalone). The
writer (the host holding the worker lock) fills Milvus from the store's codes and alone writes to it; the
other builds no index and writes nothing. /ready and /metrics name the kind; an upload through the other
host is found first through both once its job is done, and a delete through it is gone from both at once."""

from __future__ import annotations

import time

import pytest

from tests.api.conftest import Server, wait_job
from tests.api.test_postgres_hosts import NEW_PHOTOS, _locate, _upload, hosts_env, pg_template  # noqa: F401

pytestmark = pytest.mark.milvus


def test_two_hosts_share_one_milvus_collection(tmp_path, fitted_models, hosts_env, milvus_server):  # noqa: F811
    env = {**hosts_env, "GEOLOC_MILVUS_URI": milvus_server.uri, "GEOLOC_MILVUS_COLLECTION": "hosts"}
    a = Server(tmp_path / "host-a", fitted_models, extra_env=env)
    b = None
    try:
        ready_a = a.wait_ready()
        assert ready_a["worker"] == "in-process" and ready_a["index_loaded"] == "shared", ready_a
        assert {p: s["kind"] for p, s in ready_a["index"].items()} == {"float": "milvus", "binary": "milvus"}
        assert "milvus at every size" in ready_a["index_choice"]
        deadline = time.monotonic() + 60
        while a.client.get("/ready").json()["index_size"] != 30:  # the writer's first catch-up fills Milvus
            assert time.monotonic() < deadline, a.read_log()
            time.sleep(0.5)
        metrics = a.client.get("/metrics").text
        assert "geoloc_index_kind{" in metrics and 'kind="milvus"' in metrics

        b = Server(tmp_path / "host-b", fitted_models, extra_env=env)
        ready_b = b.wait_ready()
        assert ready_b["worker"] == "external" and ready_b["index_loaded"] == "shared", ready_b
        assert ready_b["index_size"] == 30 and ready_b["index"]["float"]["collection"] == "hosts_float_g0"
        assert not list((tmp_path / "host-b").rglob("index.json"))  # no snapshot anywhere on B

        # An upload through B (which does not write to Milvus) is encoded by A and found first on both.
        photo = NEW_PHOTOS[0]
        job_id, ref_id = _upload(b, photo)
        assert wait_job(b.client, job_id, 60)["status"] == "done"
        assert _locate(b, photo)[0]["reference_id"] == ref_id
        assert _locate(a, photo)[0]["reference_id"] == ref_id

        # A delete through B is gone from both at once (A's change listener applies it to Milvus).
        assert b.client.delete(f"/references/{ref_id}").status_code in (200, 204)
        assert ref_id not in [c["reference_id"] for c in _locate(b, photo)]
        assert ref_id not in [c["reference_id"] for c in _locate(a, photo)]
        assert a.client.get("/ready").json()["index_size"] == b.client.get("/ready").json()["index_size"] == 30
    finally:
        for s in (b, a):
            if s is not None:
                s.stop()


def test_milvus_stopped_answers_503_loses_nothing_and_comes_back(tmp_path, fitted_models, milvus_server):
    """A real server (SQLite store, the in-process worker: the writer) serving from Milvus: Milvus stopped,
    each of several /locate requests (one after another, not concurrent) is a 503 `not_ready` naming the
    server and saying to retry, /ready is a 503 that names it, an upload is still accepted and encoded
    into the store; Milvus started again, the same server answers again by itself in every search mode, has
    lost nothing and finds the upload made during the outage first."""
    env = {"GEOLOC_MILVUS_URI": milvus_server.uri, "GEOLOC_MILVUS_COLLECTION": "outage"}
    with Server(tmp_path / "data", fitted_models, extra_env=env) as server:
        before = []
        for photo in NEW_PHOTOS[:2]:
            job_id, ref_id = _upload(server, photo)
            assert wait_job(server.client, job_id, 60)["status"] == "done"
            before.append(ref_id)
        assert _locate(server, NEW_PHOTOS[0])[0]["reference_id"] == before[0]

        milvus_server.stop()
        try:
            image = NEW_PHOTOS[1].read_bytes()
            for _ in range(3):  # /locate keeps coming while the server is away
                r = server.client.post("/locate", files=[("image", ("q.jpg", image, "image/jpeg"))])
                assert r.status_code == 503, r.text
                body = r.json()
                assert body["error"] == "not_ready" and "Milvus server" in body["message"], body
                assert "retry" in body["message"], body
            ready = server.client.get("/ready")  # not ready, and why (a balancer sends no /locate here)
            assert ready.status_code == 503 and ready.json()["error"] == "not_ready", ready.text
            assert "Milvus server" in ready.json()["message"], ready.text
            job_id, during = _upload(server, NEW_PHOTOS[2])  # accepted, and encoded into the store
            assert wait_job(server.client, job_id, 60)["status"] == "done"
        finally:
            milvus_server.start()

        deadline = time.monotonic() + 180
        while True:  # back by itself: the writer's next catch-up reconnects and applies what it missed
            r = server.client.post("/locate", files=[("image", ("q.jpg", NEW_PHOTOS[2].read_bytes(), "image/jpeg"))])
            if r.status_code == 200 and r.json()["candidates"][0]["reference_id"] == during:
                break
            assert r.status_code in (200, 503) and time.monotonic() < deadline, (r.text, server.read_log())
            time.sleep(1.0)
        assert [_locate(server, p)[0]["reference_id"] for p in NEW_PHOTOS[:2]] == before
        assert server.client.get("/ready").json()["index_size"] == 3  # nothing lost
        for mode in ("two-stage", "float", "binary"):  # every search mode is served again
            files = [("image", ("q.jpg", NEW_PHOTOS[1].read_bytes(), "image/jpeg"))]
            r = server.client.post("/locate", files=files, data={"mode": mode})
            assert r.status_code == 200 and r.json()["candidates"][0]["reference_id"] == before[1], (mode, r.text)
