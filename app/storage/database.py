"""The data dir's SQLite database on one connection, shared by a process's threads: write transactions,
consistent reads, and the ``meta`` table (key -> text) that every part of the store reads.

Every part of ``ReferenceStore`` (``store``, ``queue``, ``changes``, ``generations``, ``identity``,
``removals``, ``maintenance``) is a subclass of ``Database`` composed into that one class, so a transaction
can span the tables of several parts (an add writes rows, the change log, a job and the removal queue in
one commit) and callers keep one object.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from app.errors import StorageUnavailable
from app.permissions import create_private_file, private_dir
from app.storage.errors import storage_guard
from app.storage.files import IMAGES
from app.storage.integrity import DatabaseFiles

DB_NAME = "references.sqlite"
META_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


#: The setting that puts the store on PostgreSQL (``postgresql://user@host:port/db``); unset: SQLite in the
#: data dir, as always.
DATABASE_URL_ENV = "GEOLOC_DATABASE_URL"
#: With PostgreSQL, where the image files live: a path every host of a deployment mounts (see README,
#: "Several hosts"); unset, or on SQLite: ``<data dir>/images``.
IMAGES_DIR_ENV = "GEOLOC_IMAGES_DIR"
#: With PostgreSQL, where the index snapshots live: a path every host mounts, so a replica starting cold
#: loads the writer's newest snapshot (checked against the database) instead of rebuilding; unset, or on
#: SQLite: the data dir.
SNAPSHOTS_DIR_ENV = "GEOLOC_SNAPSHOTS_DIR"


def database_url() -> str | None:
    """The PostgreSQL URL when the store is on PostgreSQL, else None (SQLite)."""
    from app.storage.postgres import is_postgres_url

    url = os.environ.get(DATABASE_URL_ENV, "").strip()
    if url and not is_postgres_url(url):
        raise ValueError(f"{DATABASE_URL_ENV} must be a postgresql:// URL (or unset for SQLite), not {url!r}")
    return url or None


def ids_json(ids) -> str:
    """Id lists of any length bind as one JSON parameter (``json_each``): SQLite caps bound variables."""
    return json.dumps([int(i) for i in ids])


class Database:
    """One connection to the store's database: SQLite in ``data_dir`` or, with ``GEOLOC_DATABASE_URL``,
    PostgreSQL (``app.storage.postgres``: the same SQL, translated); ``SCHEMAS`` (each part's tables) are
    created on a writable open. ``engine`` says which, for the few things that differ beyond spelling."""

    SCHEMAS: tuple[str, ...] = (META_SCHEMA,)

    def __init__(self, data_dir: Path, read_only: bool = False):
        self.data_dir = Path(data_dir)
        self.read_only = read_only
        self._lock = threading.RLock()
        self.database_url = database_url()
        self.engine = "postgres" if self.database_url else "sqlite"
        shared = os.environ.get(IMAGES_DIR_ENV, "").strip() if self.database_url else ""
        self._images_dir = Path(shared) if shared else self.data_dir / IMAGES
        shared = os.environ.get(SNAPSHOTS_DIR_ENV, "").strip() if self.database_url else ""
        self._snapshots_dir = Path(shared) if shared else self.data_dir
        #: The SQLite files this process writes through (None: read-only, or PostgreSQL's server owns them).
        self.files: DatabaseFiles | None = None
        with storage_guard("opening the data dir"):
            if self.database_url:
                self._open_postgres(read_only)
                return
            if read_only:
                uri = f"file:{self.data_dir / DB_NAME}?mode=ro"
                self.db = sqlite3.connect(uri, uri=True, check_same_thread=False, isolation_level=None)
            else:
                private_dir(self.data_dir, parents=True)
                private_dir(self.data_dir / IMAGES)
                create_private_file(self.data_dir / DB_NAME)
                self.db = sqlite3.connect(self.data_dir / DB_NAME, check_same_thread=False, isolation_level=None)
                self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.execute("PRAGMA busy_timeout=10000")
            # 64 MB of page cache (default 2 MB): bulk inserts into the sha256 index of a million rows touch
            # pages all over it, and seeding slowed from 2,000 to 800 rows/s past 600k rows without it.
            self.db.execute("PRAGMA cache_size=-65536")
            if not read_only:
                for schema in self.SCHEMAS:
                    self.db.executescript(schema)
                self.files = DatabaseFiles(self.data_dir / DB_NAME)

    def _open_postgres(self, read_only: bool) -> None:
        """The rows on PostgreSQL; the data dir still holds this host's snapshots and locks, and the images
        folder (a shared path across hosts: ``GEOLOC_IMAGES_DIR``)."""
        from app.storage.postgres import PostgresConnection

        if not read_only:
            private_dir(self.data_dir, parents=True)
            private_dir(self.images_dir, parents=True)
            private_dir(self.snapshots_dir, parents=True)
        self.db = PostgresConnection(self.database_url, read_only)
        if not read_only:
            self.db.executescript("\n".join(self.SCHEMAS))

    def close(self) -> None:
        self.db.close()

    @property
    def images_dir(self) -> Path:
        return self._images_dir

    @property
    def snapshots_dir(self) -> Path:
        """Where the index snapshots are written and loaded (the data dir, or a shared path on PostgreSQL)."""
        return self._snapshots_dir

    def _notify(self, db) -> None:
        """Inside a write transaction that changes the index: on PostgreSQL, wake every replica at commit
        (``ChangeListener``); SQLite's processes share a host and catch up at their next search."""
        if self.engine == "postgres":
            db.notify()

    def image_path_for(self, sha: str, ext: str) -> Path:
        return self.images_dir / f"{sha}.{ext}"

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE: the write lock is taken up front, so two processes never
        both read-then-write on stale data); storage failures come out as ``StorageUnavailable``."""
        with self._lock, storage_guard("writing the database"):
            self.check_files()
            self.db.execute("BEGIN IMMEDIATE")
            try:
                yield self.db
                self.db.execute("COMMIT")
            except BaseException:
                if self.db.in_transaction:
                    self.db.execute("ROLLBACK")
                raise

    @property
    def write_refusal(self) -> str | None:
        """Why this process refuses every write (its database files changed under it), or None."""
        return self.files.refusal if self.files is not None else None

    def check_files(self) -> None:
        """Before a write: refuse it (``StorageUnavailable``) once the database files are not the ones this
        process opened (``app.storage.integrity``)."""
        if self.files is None:
            return
        if self.files.refusal is None and (why := self.files.changed()) is not None:
            self.refuse_writes(why)
        if self.files.refusal is not None:
            raise StorageUnavailable(self.files.refusal)

    def refuse_writes(self, why: str) -> None:
        """From now on every write is refused, saying ``why``; what this connection sees is copied aside."""
        if self.files is not None:
            with self._lock:
                self.files.refuse(why, self.db)

    def fetch_bulk(self, db, sql: str) -> list[tuple]:
        """Every row of a bulk read (all the codes: a cold start, a new generation). On PostgreSQL in the
        binary format: BYTEA codes travel as stored instead of as hex text, half the bytes and no decoding
        (a cold read of 10^5 codes: 0.85 s in text, 0.44 s in binary; docs/BENCHMARKS.md)."""
        if self.engine == "postgres":
            return db.execute(sql, binary=True).fetchall()
        return db.execute(sql).fetchall()

    @contextmanager
    def read_snapshot(self) -> Iterator[sqlite3.Connection]:
        """Several reads that must see one consistent state (WAL readers keep their snapshot until COMMIT)."""
        with self._lock:
            self.db.execute("BEGIN")
            try:
                yield self.db
            finally:
                self.db.execute("COMMIT")

    # -- meta -----------------------------------------------------------------------------------------
    def get_meta(self, key: str) -> str | None:
        row = self.db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return row[0] if row else None

    def set_meta(self, key: str, value: str) -> None:
        with storage_guard("writing the database"):
            self.check_files()
            self.db.execute(
                "INSERT INTO meta(key, value) VALUES(?, ?) ON CONFLICT(key) DO UPDATE SET value=excluded.value",
                (key, value),
            )

    def _fingerprint_is(self, db: sqlite3.Connection, fingerprint: str) -> bool:
        row = db.execute("SELECT value FROM meta WHERE key='fingerprint'").fetchone()
        return row is None or row[0] == fingerprint


def blob(code: np.ndarray | None, dtype) -> bytes | None:
    """A code as stored in its BLOB column (None stays NULL)."""
    return None if code is None else np.asarray(code, dtype).tobytes()
