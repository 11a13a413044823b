"""Several hosts on one PostgreSQL database: two real uvicorn servers, each with a data dir of its own (its
snapshots, its lock files, its API key) and the images on one shared path, as two hosts would run them.
An upload on one is found first by /locate on the other, a PATCH and a delete show on both, a refit on one
switches both, and kill -9 of the writer's process hands the role to the other within seconds, every queued
upload encoded once."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from app.apikey import key_path, read_key
from app.manifests import read_manifest
from tests.api.conftest import CONFIG, Server, wait_job
from tests.conftest import PENN

#: Photos the mini collection does not hold (its captures are the penn index's first 16).
NEW_PHOTOS = [PENN / "crops" / f"img_000{n}_0.jpg" for n in (40, 41, 42, 43)]
#: From kill -9 of the holder to the other server holding the role (it retries every second here).
TAKEOVER_S = 15.0


@pytest.fixture(scope="module")
def pg_template(postgres_server, tmp_path_factory, fitted_models, mini_manifest):
    """The mini manifest's 30 db images ingested once by `geoloc ingest` into a database on the session's
    server (a template each test copies) and a shared images folder."""
    url = postgres_server.create_database()
    root = tmp_path_factory.mktemp("pg-collection")
    env = {**os.environ, "GEOLOC_DATABASE_URL": url, "GEOLOC_IMAGES_DIR": str(root / "images")}
    args = ["ingest", "--manifest", str(mini_manifest), "--split", "db", "--config", CONFIG]
    args += ["--data-dir", str(root / "ingest"), "--models-dir", str(fitted_models)]
    out = subprocess.run(
        [sys.executable, "-m", "app.cli", *args],
        capture_output=True, text=True, timeout=600, env=env,
    )  # fmt: skip
    assert "ingested 30 new references" in out.stdout, out.stdout + out.stderr
    return url.rsplit("/", 1)[1], root / "images"


@pytest.fixture
def hosts_env(postgres_server, pg_template, tmp_path) -> dict:
    """A fresh copy of the template database and of the images: the environment every "host" shares."""
    import psycopg

    template, images = pg_template
    name = f"h_{os.getpid()}_{time.monotonic_ns()}"
    with psycopg.connect(postgres_server.url(), autocommit=True) as con:
        con.execute(f'CREATE DATABASE "{name}" TEMPLATE "{template}"')
    shutil.copytree(images, tmp_path / "images")
    return {
        "GEOLOC_DATABASE_URL": postgres_server.url(name),
        "GEOLOC_IMAGES_DIR": str(tmp_path / "images"),
        "GEOLOC_SNAPSHOTS_DIR": str(tmp_path / "snapshots"),
        "GEOLOC_WORKER_RETRY_SECONDS": "1",
    }


def _upload(server: Server, photo: Path) -> tuple[str, int]:
    r = server.client.post(
        "/references",
        files=[("image", (photo.name, photo.read_bytes(), "image/jpeg"))],
        data={"metadata": json.dumps([{"lat": 39.95, "lon": -75.19, "label": photo.name}])},
    )
    assert r.status_code == 202, r.text
    return r.json()["job_id"], r.json()["reference_ids"][0]


def _locate(server: Server, photo: Path) -> list[dict]:
    r = server.client.post("/locate", files=[("image", ("q.jpg", photo.read_bytes(), "image/jpeg"))])
    assert r.status_code == 200, r.text
    return r.json()["candidates"]


def test_two_hosts_on_one_database_see_each_others_changes(tmp_path, fitted_models, hosts_env, mini_manifest):
    """Then `geoloc refit` on one host re-encodes every reference (images read from the shared path) and
    switches the generation in the database: both servers load it without a restart. The hosts share one
    `pipelines/` folder (a symlink here; a shared mount in a deployment), as README 'Several hosts' says."""
    from app.manifests import read_manifest

    (tmp_path / "host-a" / "pipelines").mkdir(parents=True)
    (tmp_path / "host-b").mkdir()
    (tmp_path / "host-b" / "pipelines").symlink_to(tmp_path / "host-a" / "pipelines")
    a = Server(tmp_path / "host-a", fitted_models, extra_env=hosts_env)
    b = None
    try:
        ready_a = a.wait_ready()
        assert ready_a["database"] == "postgres" and ready_a["worker"] == "in-process"
        # A started cold (no snapshot yet): it rebuilt its index from the database's codes, and writes a
        # snapshot into the shared folder right after; B, starting then, loads that snapshot.
        assert ready_a["index_loaded"] == "rebuilt", ready_a
        deadline = time.monotonic() + 60
        while not (Path(hosts_env["GEOLOC_SNAPSHOTS_DIR"]) / "index.json").exists():
            assert time.monotonic() < deadline, a.read_log()
            time.sleep(0.2)
        b = Server(tmp_path / "host-b", fitted_models, extra_env=hosts_env)
        ready_b = b.wait_ready()
        assert ready_b["worker"] == "external" and ready_b["index_loaded"] == "snapshot", ready_b
        assert ready_b["index_size"] == 30

        # An upload on B (which does not hold the writer role) is encoded by A and found first on both.
        photo = NEW_PHOTOS[0]
        job_id, ref_id = _upload(b, photo)
        assert wait_job(b.client, job_id, 60)["status"] == "done"
        assert _locate(a, photo)[0]["reference_id"] == ref_id
        assert _locate(b, photo)[0]["reference_id"] == ref_id
        thumb = b.client.get(f"/references/{ref_id}/image")  # the image from the shared path, on either host
        assert thumb.status_code == 200 and thumb.headers["content-type"] == "image/jpeg"

        # A PATCH on A shows on B; a delete on B shows on A (metadata, search and the image).
        r = a.client.patch(f"/references/{ref_id}", json={"label": "moved", "lat": 39.951})
        assert r.status_code == 200, r.text
        got = b.client.get(f"/references/{ref_id}").json()
        assert got["label"] == "moved" and got["lat"] == pytest.approx(39.951)
        assert b.client.delete(f"/references/{ref_id}").status_code == 200
        assert a.client.get(f"/references/{ref_id}").status_code == 404
        assert ref_id not in [c["reference_id"] for c in _locate(a, photo)]
        assert a.client.get("/ready").json()["index_size"] == b.client.get("/ready").json()["index_size"] == 30
        assert "Traceback" not in a.read_log() + b.read_log()

        # A refit on host A switches both hosts.
        known = next(r for r in read_manifest(mini_manifest) if r.split == "db").image
        own_id = _locate(b, known)[0]["reference_id"]
        out = subprocess.run(
            [sys.executable, "-m", "app.cli", "refit", "--data-dir", str(tmp_path / "host-a"),
             "--models-dir", str(fitted_models), "--sample", "12", "--svm-bank", "none", "--seed", "7"],
            capture_output=True, text=True, timeout=600, env={**os.environ, **hosts_env},
        )  # fmt: skip
        assert out.returncode == 0 and "30 references re-encoded" in out.stdout, out.stdout + out.stderr
        for server in (a, b):
            deadline = time.monotonic() + 120
            while server.client.get("/ready").json()["generation"] != 1:
                assert time.monotonic() < deadline, server.read_log()
                time.sleep(0.2)
            top = _locate(server, known)[0]
            assert top["reference_id"] == own_id and top["score"] > 0.99
    finally:
        a.stop()
        if b is not None:
            b.stop()


def test_kill_9_of_the_writer_hands_the_role_over_and_uploads_are_encoded_once(tmp_path, fitted_models, hosts_env):
    """First the writer's database session is cut (what a restart of the server or a network cut does to
    it): the holder notices and gives the role up, and one process holds it again. Then the holder is
    killed with SIGKILL while uploads are queued: the other takes the role within seconds and every queued
    upload is indexed exactly once."""
    import psycopg

    from app.storage.postgres import WRITER_ROLE_KEY

    url = hosts_env["GEOLOC_DATABASE_URL"]
    a = Server(tmp_path / "host-a", fitted_models, extra_env=hosts_env)
    b = None
    try:
        assert a.wait_ready()["worker"] == "in-process"
        b = Server(tmp_path / "host-b", fitted_models, extra_env=hosts_env)
        assert b.wait_ready()["worker"] == "external"

        with psycopg.connect(url, autocommit=True) as con:
            cut = con.execute(
                "SELECT pg_terminate_backend(pid) FROM pg_locks WHERE locktype = 'advisory' AND granted "
                "AND ((classid::bigint << 32) | objid::bigint) = %s",
                (WRITER_ROLE_KEY,),
            ).fetchall()
        assert cut == [(True,)]
        deadline = time.monotonic() + TAKEOVER_S
        while True:
            roles = {s: s.client.get("/ready").json()["worker"] for s in (a, b)}
            if "lost the worker lock" in a.read_log() and list(roles.values()).count("in-process") == 1:
                break
            assert time.monotonic() < deadline, (roles, a.read_log())
            time.sleep(0.2)
        holder = next(s for s, role in roles.items() if role == "in-process")
        other = b if holder is a else a

        jobs = [_upload(other, p) for p in NEW_PHOTOS]  # queued in the database; the holder starts on them
        holder.kill()
        killed = time.monotonic()
        while other.client.get("/ready").json()["worker"] != "in-process":
            assert time.monotonic() - killed < TAKEOVER_S, other.read_log()
            time.sleep(0.2)
        for job_id, _ in jobs:
            assert wait_job(other.client, job_id, 60)["status"] == "done"
        assert "took over the worker lock" in other.read_log()
        for photo, (_, ref_id) in zip(NEW_PHOTOS, jobs, strict=True):
            assert _locate(other, photo)[0]["reference_id"] == ref_id
        with psycopg.connect(url) as con:
            adds = con.execute("SELECT ref_id, COUNT(*) FROM changes WHERE op='add' GROUP BY ref_id").fetchall()
            indexed = con.execute("SELECT COUNT(*) FROM refs WHERE status='indexed'").fetchone()[0]
        assert indexed == 34 and len(adds) == 34 and all(n == 1 for _, n in adds)  # exactly once each
        assert other.client.get("/ready").json()["index_size"] == 34
    finally:
        a.stop()
        if b is not None:
            b.stop()


def test_check_backup_and_restore_on_postgres(tmp_path, fitted_models, hosts_env, postgres_server):
    """`geoloc check` reads the database and the shared images; `geoloc backup` is a pg_dump and the images
    its rows name, of one state; `geoloc restore` puts both into an empty database and images folder, which
    then checks clean and serves the same collection."""
    env = {**os.environ, **hosts_env}
    base = [sys.executable, "-m", "app.cli"]
    where = ["--data-dir", str(tmp_path / "host-c")]
    models = ["--models-dir", str(fitted_models), "--config", CONFIG]

    def run(*args, environ=env):
        return subprocess.run([*base, *args], capture_output=True, text=True, timeout=300, env=environ)

    out = run("check", *where, *models)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "rows: 30 indexed, 0 pending, 0 failed" in out.stdout and "images: 30 files, 0 missing" in out.stdout
    out = run("backup", str(tmp_path / "bk"), *where)
    assert out.returncode == 0 and "backed up 30 references (30 images" in out.stdout, out.stdout + out.stderr
    assert (tmp_path / "bk" / "database.dump").stat().st_size > 0
    # An image lost from the shared folder is a problem the check names.
    victim = sorted(p for p in Path(hosts_env["GEOLOC_IMAGES_DIR"]).iterdir() if not p.name.startswith("."))[0]
    victim.unlink()
    out = run("check", *where, *models)
    assert out.returncode == 1 and "image file is missing" in out.stderr, out.stdout + out.stderr
    # Restored into a new database and images folder: a clean check, and a server that finds the lost photo.
    restored = {**env, "GEOLOC_DATABASE_URL": postgres_server.create_database()}
    restored["GEOLOC_IMAGES_DIR"] = str(tmp_path / "restored-images")
    out = run("restore", str(tmp_path / "bk"), "--data-dir", str(tmp_path / "restored"), environ=restored)
    assert out.returncode == 0, out.stdout + out.stderr
    assert (tmp_path / "restored-images" / victim.name).exists()
    out = run("check", "--data-dir", str(tmp_path / "restored"), *models, environ=restored)
    assert out.returncode == 0 and "rows: 30 indexed" in out.stdout, out.stdout + out.stderr
    # A restore never merges into a database that holds a collection.
    out = run("restore", str(tmp_path / "bk"), "--data-dir", str(tmp_path / "again"), environ=restored)
    assert out.returncode != 0 and "new, empty database" in out.stdout + out.stderr


def _writer_sessions(url: str) -> list[int]:
    """The server-side pids of the sessions holding the writer role's advisory lock."""
    import psycopg

    from app.storage.postgres import WRITER_ROLE_KEY

    with psycopg.connect(url, autocommit=True) as con:
        rows = con.execute(
            "SELECT pid FROM pg_locks WHERE locktype = 'advisory' AND granted "
            "AND ((classid::bigint << 32) | objid::bigint) = %s",
            (WRITER_ROLE_KEY,),
        ).fetchall()
    return [r[0] for r in rows]


def _wait_for(what: str, ok, log: Path, timeout: float = TAKEOVER_S) -> None:
    deadline = time.monotonic() + timeout
    while not ok():
        assert time.monotonic() < deadline, f"{what}: {log.read_text()[-3000:]}"
        time.sleep(0.2)


def test_standalone_worker_gives_the_role_up_when_its_session_is_cut(tmp_path, fitted_models, hosts_env):
    """`geoloc worker` on PostgreSQL: its lock's session is terminated on the server (what a restart or a
    network cut does); it notices, stops encoding while another session holds the role (an upload stays
    pending), and takes the role again once that one lets it go, then encodes the upload."""
    import psycopg

    from app.storage.postgres import WRITER_ROLE_KEY

    url = hosts_env["GEOLOC_DATABASE_URL"]
    log = tmp_path / "worker.log"
    env = {**os.environ, **hosts_env, "PYTHONUNBUFFERED": "1", "GEOLOC_ORT_THREADS": "1"}
    worker = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "worker", "--data-dir", str(tmp_path / "worker"),
         "--models-dir", str(fitted_models), "--config", CONFIG, "--batch", "4"],
        stdout=log.open("a"), stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    api = Server(tmp_path / "api", fitted_models, extra_env=hosts_env, worker="none")
    other = None
    try:
        api.wait_ready()
        _wait_for("the worker holds the role", lambda: "pending" in log.read_text(), log, 120)
        (held,) = _writer_sessions(url)
        job_id, ref_id = _upload(api, NEW_PHOTOS[0])  # encoded by the worker: it works while it holds the role
        assert wait_job(api.client, job_id, 60)["status"] == "done"

        # Another holder, connected beforehand, asks for the role as soon as the session is cut: the worker
        # needs a check period and a retry period (2 s) to ask again, so on a loaded machine it cannot win.
        other = psycopg.connect(url, autocommit=True)
        with psycopg.connect(url, autocommit=True) as con:
            assert con.execute("SELECT pg_terminate_backend(%s)", (held,)).fetchone()[0]
        deadline = time.monotonic() + TAKEOVER_S
        while not other.execute("SELECT pg_try_advisory_lock(%s)", (WRITER_ROLE_KEY,)).fetchone()[0]:
            assert time.monotonic() < deadline, f"another session takes the role: {log.read_text()[-3000:]}"
            time.sleep(0.02)
        _wait_for("the worker notices", lambda: "lost the worker lock" in log.read_text(), log)
        assert worker.poll() is None  # the worker waits for the role; it did not exit
        job_id, ref_id = _upload(api, NEW_PHOTOS[1])
        time.sleep(4)  # the worker checks every second: it would have encoded it by now if it still worked
        assert api.client.get(f"/references/{ref_id}").json()["status"] == "pending"

        other.close()  # the role is free again: the worker takes it and encodes what waits
        other = None
        assert wait_job(api.client, job_id, 60)["status"] == "done"
        assert "took over the worker lock" in log.read_text() and len(_writer_sessions(url)) == 1
        assert _locate(api, NEW_PHOTOS[1])[0]["reference_id"] == ref_id
        worker.send_signal(signal.SIGTERM)
        assert worker.wait(60) == 0, log.read_text()[-3000:]
        assert "Traceback" not in log.read_text()
    finally:
        if other is not None:
            other.close()
        api.stop()
        if worker.poll() is None:
            worker.kill()
            worker.wait()


def test_a_poison_reference_leaves_both_replicas_serving(tmp_path, fitted_models, hosts_env, monkeypatch):
    """A strip of 49000 x 32 pixels stored pending (as an older version accepted it) once killed the
    writer, then the next host to take the role. Now it fails alone with its reason: both hosts
    keep serving and the rest of its batch is indexed."""
    from tests.api.test_hardening_shapes import _add_pending
    from tools.crafted_images import STRIPS

    for name, value in hosts_env.items():
        monkeypatch.setenv(name, value)
    ids, job_id = _add_pending(
        tmp_path / "seed",
        [(NEW_PHOTOS[0].read_bytes(), "jpg"), (STRIPS["49000x32 png"](), "png"), (NEW_PHOTOS[1].read_bytes(), "jpg")],
    )
    a = Server(tmp_path / "host-a", fitted_models, extra_env=hosts_env)
    b = Server(tmp_path / "host-b", fitted_models, extra_env=hosts_env)
    with a, b:
        job = wait_job(b.client, job_id, 120)
        status = {it["reference_id"]: it["status"] for it in job["items"]}
        assert [status[i] for i in ids] == ["indexed", "failed", "indexed"], job
        for host in (a, b):
            assert host.client.get("/health").status_code == 200
            assert host.proc.poll() is None
            assert _locate(host, NEW_PHOTOS[1])[0]["reference_id"] == ids[2]


def test_a_host_without_the_shared_images_folder_refuses_to_serve(tmp_path, fitted_models, hosts_env):
    """Two servers on one database, each with its own data dir and GEOLOC_IMAGES_DIR left out: the first
    serves, the second never gets ready and says why on /ready (uploads there used to be accepted and never
    found by the writer); uploads to it are refused, not lost."""
    env = {k: v for k, v in hosts_env.items() if k != "GEOLOC_IMAGES_DIR"}
    with Server(tmp_path / "host-a", fitted_models, extra_env=env) as a:
        b = Server(tmp_path / "host-b", fitted_models, extra_env=env)
        try:
            deadline = time.monotonic() + 120
            while True:
                assert time.monotonic() < deadline, b.read_log()
                try:
                    r = b.client.get("/ready")
                except httpx.TransportError:  # not listening yet
                    time.sleep(0.5)
                    continue
                if r.status_code == 503 and "GEOLOC_IMAGES_DIR" in r.json()["message"]:
                    break
                assert r.status_code != 200, "the second host serves with an images folder no other host reads"
                time.sleep(0.5)
            assert "one shared folder" in r.json()["message"]
            photo = NEW_PHOTOS[0]
            b.client.headers["X-API-Key"] = read_key(key_path(tmp_path / "host-b"))
            up = b.client.post("/references", files=[("image", (photo.name, photo.read_bytes(), "image/jpeg"))])
            assert up.status_code == 503, up.text
            assert a.client.get("/ready").status_code == 200
        finally:
            b.stop()


def test_an_app_built_from_settings_keeps_its_lock_and_rows_on_postgres(
    tmp_path, fitted_models, hosts_env, mini_manifest, monkeypatch
):
    """Settings are read once, where a process starts, and passed down: an app built from
    ``Settings(database_url=...)`` with no GEOLOC_* variable takes PostgreSQL's writer role and writes its
    rows there, never SQLite's lock file in its data dir."""
    import threading

    import psycopg
    import uvicorn

    from app.api.app import create_app
    from app.settings import Settings
    from tools.server_process import free_port

    for name in list(os.environ):
        if name.startswith("GEOLOC_"):
            monkeypatch.delenv(name)
    url = hosts_env["GEOLOC_DATABASE_URL"]
    data = tmp_path / "data"
    settings = Settings(
        data_dir=data, models_dir=fitted_models, config=CONFIG, database_url=url, api_key="settings-key",
        images_dir=Path(hosts_env["GEOLOC_IMAGES_DIR"]), snapshots_dir=Path(hosts_env["GEOLOC_SNAPSHOTS_DIR"]),
        ort_threads=1,
    )  # fmt: skip
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60, headers={"X-API-Key": "settings-key"})
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if client.get("/ready").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        photo = next(r.image for r in read_manifest(mini_manifest) if r.split == "query")
        r = client.post("/references", files=[("image", (photo.name, photo.read_bytes(), "image/jpeg"))],
                        data={"metadata": json.dumps([{"lat": 39.95, "lon": -75.19}])})  # fmt: skip
        assert r.status_code == 202, r.text
        assert wait_job(client, r.json()["job_id"])["status"] == "done"
        assert _writer_sessions(url), "the writer role is not PostgreSQL's advisory lock"
        with psycopg.connect(url) as con:
            assert con.execute("SELECT COUNT(*) FROM refs").fetchone()[0] == 31
        assert not (data / "references.sqlite").exists() and not (data / "worker.lock").exists()
    finally:
        server.should_exit = True
        thread.join(60)
