"""What only PostgreSQL does: replicas woken by NOTIFY when an index change commits (not by an accepted
upload, which changes no index), and the writer role held by an advisory lock that dies with its session."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from app.ingestion.worker import writer_lock
from app.storage.postgres import ChangeListener, DatabaseWriterLock
from app.storage.settings import StorageSettings
from app.storage.store import NewReference, ReferenceStore


def _item(rng, encoded: bool) -> NewReference:
    code = rng.standard_normal(8).astype(np.float32) if encoded else None
    return NewReference(rng.bytes(64), "jpg", 40.0, -75.0, float_code=code)


def test_a_committed_index_change_wakes_the_listener(tmp_path, postgres_server, monkeypatch):
    url = postgres_server.create_database()
    store = ReferenceStore(tmp_path, backend=StorageSettings(database_url=url).backend(tmp_path))
    woke = threading.Event()
    listener = ChangeListener(url, woke.set).start()
    try:
        assert woke.wait(10)  # the catch-up it does once listening
        woke.clear()
        rng = np.random.default_rng(0)
        store.add_many([_item(rng, encoded=False)])  # accepted, pending: no index change, no wake-up
        assert not woke.wait(1.5)
        store.add_many([_item(rng, encoded=True)])
        assert woke.wait(5) and store.version == 1
    finally:
        listener.stop()
        store.close()


def test_the_writer_role_is_one_advisory_lock_released_with_its_session(tmp_path, postgres_server, monkeypatch):
    monkeypatch.setenv("GEOLOC_DATABASE_URL", postgres_server.create_database())
    url = postgres_server.create_database()  # two hosts' data dirs, one database
    first, second = (writer_lock(StorageSettings(database_url=url).backend(tmp_path / d)) for d in "ab")
    assert isinstance(first, DatabaseWriterLock)
    assert first.acquire() and not second.acquire() and first.alive()
    first._conn.close()  # the holder's session ends (its process died): the lock goes with it
    assert not first.alive() and second.acquire() and second.alive()
    second.release()


def test_a_database_server_that_goes_away_is_a_storage_error_and_comes_back(tmp_path, postgres_server, monkeypatch):
    """The server stopped under a running store (a restart, a failover of the database): every call says
    "storage unavailable" (a 503 the client retries), nothing stored is lost, and once the server is back
    the same store works again without being reopened."""
    from app.errors import StorageUnavailable
    from tools.postgres_server import PostgresServer

    server = PostgresServer().start()  # a server of this test's own: it is stopped and started again
    try:
        url = server.create_database()
        store = ReferenceStore(tmp_path, backend=StorageSettings(database_url=url).backend(tmp_path))
        rng = np.random.default_rng(2)
        store.add_many([_item(rng, encoded=True)])
        server.stop_server()
        for call in (lambda: store.add_many([_item(rng, encoded=True)]), lambda: store.count(None), store.head):
            with pytest.raises(StorageUnavailable):
                call()
        server.start_server()
        assert store.count(None) == 1 and store.version == 1
        store.add_many([_item(rng, encoded=True)])
        # Versions keep rising (a crashed server's sequences skip ahead: gaps, never a version twice).
        assert store.count(None) == 2 and store.version > 1
        assert [c.op for c in store.changes_since(1)] == ["add"]
    finally:
        server.stop()


def test_the_client_tools_get_the_password_in_their_environment_not_on_their_command_line():
    """pg_dump and pg_restore run with the URL's password in PGPASSWORD: a command line is readable by every
    local user (`ps`), a process's environment is not."""
    pytest.importorskip("psycopg")
    from app.storage.postgres import _client_conninfo

    conninfo, env = _client_conninfo("postgresql://geoloc:s3cret@db.internal:5433/geoloc?sslmode=require")
    assert "s3cret" not in conninfo and env["PGPASSWORD"] == "s3cret"
    for part in ("host=db.internal", "port=5433", "dbname=geoloc", "user=geoloc", "sslmode=require"):
        assert part in conninfo, conninfo
    conninfo, env = _client_conninfo("postgresql://geoloc@db.internal/geoloc")
    assert "password" not in conninfo and env.get("PGPASSWORD") == os.environ.get("PGPASSWORD")
