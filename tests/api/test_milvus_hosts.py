"""Two hosts on one PostgreSQL store and one Milvus collection: two real uvicorn servers with data dirs of
their own, GEOLOC_MILVUS_URI naming the session's Milvus (the ``milvus`` wheel's embedded standalone). The
writer (the host holding the worker lock) fills Milvus from the store's codes and alone writes to it; the
other builds no index and writes nothing. /ready and /metrics name the kind; an upload through the other
host is found first through both once its job is done, and a delete through it is gone from both at once."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
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


class _Load:
    """Threads sending /locate back to back, each on its own connection, until ``stop``: every answer's
    status and error kept with the phase it was sent in and the one it was answered in (one sent just before
    Milvus stops may find it gone), and any exception (a refused connection, a timeout)."""

    def __init__(self, server: Server, photo: Path, threads: int = 2):
        self.phase, self.answers, self.failures = "before", [], []
        self._stop = threading.Event()
        self._image = photo.read_bytes()
        self._threads = [threading.Thread(target=self._run, args=(server,), daemon=True) for _ in range(threads)]

    def _run(self, server: Server) -> None:
        with httpx.Client(base_url=server.url, headers=server.client.headers, timeout=60) as client:
            while not self._stop.is_set():
                phase = self.phase
                try:
                    r = client.post("/locate", files=[("image", ("q.jpg", self._image, "image/jpeg"))])
                    body = r.json()
                    self.answers.append((phase, self.phase, r.status_code, body.get("error"), body.get("message", "")))
                except Exception as e:  # noqa: BLE001 (kept and asserted on: the test fails with it)
                    self.failures.append((phase, repr(e)))

    def __enter__(self) -> _Load:
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(90)

    def statuses(self, phase: str) -> list[int]:
        """Statuses of the requests sent and answered in ``phase``."""
        return [status for sent, answered, status, _, _ in self.answers if sent == answered == phase]


def test_milvus_stopped_under_load_answers_503_loses_nothing_and_comes_back(tmp_path, fitted_models, milvus_server):
    """A real server (SQLite store, the in-process worker: the writer) serving from Milvus while two clients
    send /locate back to back: Milvus stopped, every answer is a 200 (in flight before it went) or a 503
    `not_ready` naming the server and saying to retry, never an error of another kind nor a dropped
    connection; /ready is a 503 that names it; uploads sent meanwhile are accepted and encoded into the
    store. Milvus started again, the same server answers again by itself in every search mode, has lost
    nothing and finds the uploads made during the outage first."""
    env = {"GEOLOC_MILVUS_URI": milvus_server.uri, "GEOLOC_MILVUS_COLLECTION": "outage"}
    with Server(tmp_path / "data", fitted_models, extra_env=env) as server:
        before = []
        for photo in NEW_PHOTOS[:2]:
            job_id, ref_id = _upload(server, photo)
            assert wait_job(server.client, job_id, 60)["status"] == "done"
            before.append(ref_id)
        assert _locate(server, NEW_PHOTOS[0])[0]["reference_id"] == before[0]

        with _Load(server, NEW_PHOTOS[1]) as load:
            while len(load.statuses("before")) < 4:
                time.sleep(0.2)
            load.phase = "down"
            milvus_server.stop()
            try:
                deadline = time.monotonic() + 60
                while load.statuses("down").count(503) < 6:  # /locate keeps coming while the server is away
                    assert time.monotonic() < deadline and not load.failures, (load.answers, load.failures)
                    time.sleep(0.2)
                ready = server.client.get("/ready")  # not ready, and why (a balancer sends no /locate here)
                assert ready.status_code == 503 and ready.json()["error"] == "not_ready", ready.text
                assert "Milvus server" in ready.json()["message"], ready.text
                during = [_upload(server, photo) for photo in NEW_PHOTOS[2:]]  # accepted, encoded into the store
                assert [wait_job(server.client, job_id, 60)["status"] for job_id, _ in during] == ["done", "done"]
            finally:
                load.phase = "restarting"
                milvus_server.start()

            deadline = time.monotonic() + 180
            while True:  # back by itself: the writer's next catch-up reconnects and applies what it missed
                found = [_first(server, photo) for photo in NEW_PHOTOS[2:]]
                if found == [ref_id for _, ref_id in during]:
                    break
                assert time.monotonic() < deadline, (found, server.read_log())
                time.sleep(1.0)
            load.phase = "after"
            while len(load.statuses("after")) < 4:
                time.sleep(0.2)

        assert not load.failures, load.failures
        assert {status for _, _, status, _, _ in load.answers} <= {200, 503}, load.answers
        for _, _, status, error, message in load.answers:
            if status == 503:
                assert error == "not_ready" and "Milvus server" in message and "retry" in message, message
        assert set(load.statuses("before")) == set(load.statuses("after")) == {200}
        assert [_locate(server, p)[0]["reference_id"] for p in NEW_PHOTOS[:2]] == before
        assert server.client.get("/ready").json()["index_size"] == 4  # nothing lost
        for mode in ("two-stage", "float", "binary"):  # every search mode is served again
            files = [("image", ("q.jpg", NEW_PHOTOS[1].read_bytes(), "image/jpeg"))]
            r = server.client.post("/locate", files=files, data={"mode": mode})
            assert r.status_code == 200 and r.json()["candidates"][0]["reference_id"] == before[1], (mode, r.text)


def _first(server: Server, photo: Path) -> int | None:
    """The first candidate's reference of /locate ``photo``, or None while the server answers 503."""
    r = server.client.post("/locate", files=[("image", ("q.jpg", photo.read_bytes(), "image/jpeg"))])
    assert r.status_code in (200, 503), r.text
    return r.json()["candidates"][0]["reference_id"] if r.status_code == 200 else None
