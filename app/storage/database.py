"""The store's database on one connection, shared by a process's threads: write transactions, consistent
reads, and the ``meta`` table (key -> text) that every part of the store reads.

Every part of ``ReferenceStore`` (``store``, ``queue``, ``changes``, ``generations``, ``identity``,
``removals``, ``maintenance``) holds the one ``Database`` of its store, so a transaction can span the tables
of several parts (an add writes rows, the change log, a job and the removal queue in one commit). What
differs between SQLite and PostgreSQL is the ``backend``'s (``app.storage.backend``), asked, never branched
on. A writable open upgrades the schema first (``app.storage.migrations``).
"""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from app.errors import StorageUnavailable
from app.storage.backend import StorageBackend
from app.storage.errors import storage_guard
from app.storage.migrations import STEPS, Step, upgrade
from app.storage.sqlite import DB_NAME

__all__ = ["DB_NAME", "Database", "Part", "blob", "ids_json"]


def ids_json(ids) -> str:
    """Id lists of any length bind as one JSON parameter (``json_each``): SQLite caps bound variables."""
    return json.dumps([int(i) for i in ids])


class Database:
    """One connection through ``backend``; a writable open migrates the schema to ``steps``' last."""

    def __init__(self, backend: StorageBackend, read_only: bool = False, steps: tuple[Step, ...] = STEPS):
        self.backend = backend
        self.data_dir = backend.data_dir
        self.read_only = read_only
        self.lock = threading.RLock()
        #: The SQLite files this process writes through (None: read-only, or a server owns them).
        self.files = None
        with storage_guard("opening the data dir"):
            self.db = backend.connect(read_only)
            if not read_only:
                upgrade(self, steps)
                self.files = backend.integrity()

    def close(self) -> None:
        self.db.close()

    @property
    def images_dir(self) -> Path:
        return self.backend.images_dir

    @property
    def snapshots_dir(self) -> Path:
        """Where the index snapshots are written and loaded (the data dir, or a shared path on PostgreSQL)."""
        return self.backend.snapshots_dir

    def image_path_for(self, sha: str, ext: str) -> Path:
        return self.images_dir / f"{sha}.{ext}"

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE: the write lock is taken up front, so two processes never
        both read-then-write on stale data); storage failures come out as ``StorageUnavailable``."""
        with self.lock, storage_guard("writing the database"):
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
            with self.lock:
                self.files.refuse(why, self.db)

    @contextmanager
    def read_snapshot(self) -> Iterator[sqlite3.Connection]:
        """Several reads that must see one consistent state (WAL readers keep their snapshot until COMMIT)."""
        with self.lock:
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

    def fingerprint_is(self, db: sqlite3.Connection, fingerprint: str) -> bool:
        row = db.execute("SELECT value FROM meta WHERE key='fingerprint'").fetchone()
        return row is None or row[0] == fingerprint


class Part:
    """A part of the store: its queries over the store's one ``Database`` (connection, lock, backend)."""

    def __init__(self, database: Database):
        self.database = database


def blob(code: np.ndarray | None, dtype) -> bytes | None:
    """A code as stored in its BLOB column (None stays NULL)."""
    return None if code is None else np.asarray(code, dtype).tobytes()
