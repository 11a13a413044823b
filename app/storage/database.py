"""The data dir's SQLite database on one connection, shared by a process's threads: write transactions,
consistent reads, and the ``meta`` table (key -> text) that every part of the store reads.

Every part of ``ReferenceStore`` (``store``, ``queue``, ``changes``, ``generations``, ``identity``,
``removals``, ``maintenance``) is a subclass of ``Database`` composed into that one class, so a transaction
can span the tables of several parts (an add writes rows, the change log, a job and the removal queue in
one commit) and callers keep one object.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from app.permissions import create_private_file, private_dir
from app.storage.errors import storage_guard
from app.storage.files import IMAGES

DB_NAME = "references.sqlite"
META_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


def ids_json(ids) -> str:
    """Id lists of any length bind as one JSON parameter (``json_each``): SQLite caps bound variables."""
    return json.dumps([int(i) for i in ids])


class Database:
    """One SQLite connection to ``data_dir``'s database; ``SCHEMAS`` (each part's tables) are created on a
    writable open."""

    SCHEMAS: tuple[str, ...] = (META_SCHEMA,)

    def __init__(self, data_dir: Path, read_only: bool = False):
        self.data_dir = Path(data_dir)
        self.read_only = read_only
        self._lock = threading.RLock()
        with storage_guard("opening the data dir"):
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

    def close(self) -> None:
        self.db.close()

    @property
    def images_dir(self) -> Path:
        return self.data_dir / IMAGES

    def image_path_for(self, sha: str, ext: str) -> Path:
        return self.images_dir / f"{sha}.{ext}"

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE: the write lock is taken up front, so two processes never
        both read-then-write on stale data); storage failures come out as ``StorageUnavailable``."""
        with self._lock, storage_guard("writing the database"):
            self.db.execute("BEGIN IMMEDIATE")
            try:
                yield self.db
                self.db.execute("COMMIT")
            except BaseException:
                if self.db.in_transaction:
                    self.db.execute("ROLLBACK")
                raise

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
