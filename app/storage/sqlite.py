"""The SQLite backend (the embedded default): one file in the data dir, in WAL mode, shared by the
processes of one host.

What only SQLite does: the WAL's checkpoints into the main file (a copy of the data dir without its
``-wal`` still names its rows), ``AUTOINCREMENT``'s counters in ``sqlite_sequence``, the writer role as a
file lock in the data dir, and backups through SQLite's backup API.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import sqlite3
from collections.abc import Callable, Sequence
from pathlib import Path

from app.permissions import create_private_file, private_dir
from app.storage.backend import StorageBackend
from app.storage.files import IMAGES
from app.storage.integrity import DatabaseFiles

log = logging.getLogger("geoloc.store")

DB_NAME = "references.sqlite"


class WorkerLock:
    """One ingestion worker per data dir: a second one would encode the same rows twice."""

    def __init__(self, data_dir: Path):
        self.path = Path(data_dir) / "worker.lock"
        self._fd: int | None = None

    def acquire(self) -> bool:
        fd = os.open(self.path, os.O_CREAT | os.O_RDWR, 0o600)
        with contextlib.suppress(OSError):  # private whatever the umask (an older version made it 0644)
            os.fchmod(fd, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            return False
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        self._fd = fd
        return True

    @property
    def held(self) -> bool:
        return self._fd is not None

    #: A file lock is held until this process lets it go or dies: it cannot be lost while running.
    can_be_lost = False

    def alive(self) -> bool:
        return self.held

    @property
    def where(self) -> str:
        return str(self.path)

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


class SqliteBackend(StorageBackend):
    """The data dir's ``references.sqlite``; images in ``<data dir>/images``, snapshots in the data dir."""

    name = "sqlite"
    exceptions = (sqlite3.Error,)
    backup_name = DB_NAME

    def __init__(self, data_dir: Path):
        super().__init__(data_dir, Path(data_dir) / IMAGES, data_dir)
        self.path = self.data_dir / DB_NAME

    def connect(self, read_only: bool) -> sqlite3.Connection:
        if read_only:
            db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, check_same_thread=False, isolation_level=None)
        else:
            private_dir(self.data_dir, parents=True)
            private_dir(self.images_dir)
            create_private_file(self.path)
            db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=FULL")
        db.execute("PRAGMA busy_timeout=10000")
        # 64 MB of page cache (default 2 MB): bulk inserts into the sha256 index of a million rows touch
        # pages all over it, and seeding slowed from 2,000 to 800 rows/s past 600k rows without it.
        db.execute("PRAGMA cache_size=-65536")
        return db

    def exists(self) -> bool:
        return self.path.exists()

    def describe(self) -> str:
        return str(self.path)

    def integrity(self) -> DatabaseFiles:
        return DatabaseFiles(self.path)

    def holds_tables(self, db) -> bool:
        return db.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='refs'").fetchone() is not None

    def insert_refs(self, db, columns: Sequence[str], rows: Sequence[Sequence]) -> dict[str, tuple[int, str]]:
        """One INSERT per row: in-process calls, no round trips to save."""
        sql = (
            f"INSERT INTO refs({', '.join(columns)}) VALUES({','.join('?' * len(columns))}) "
            "ON CONFLICT(sha256) DO NOTHING RETURNING id, status"
        )
        created: dict[str, tuple[int, str]] = {}
        for row in rows:
            got = db.execute(sql, row).fetchone()
            if got is not None:
                created[row[0]] = (int(got[0]), got[1])
        return created

    def copy_rows(self, db, table: str, columns: Sequence[str], rows: Sequence[Sequence]) -> None:
        marks = ",".join("?" * len(columns))
        db.executemany(f"INSERT INTO {table}({', '.join(columns)}) VALUES({marks})", rows)

    def checkpoint(
        self, mode: str, timeout_s: float, files: DatabaseFiles | None, refuse: Callable[[str], None]
    ) -> tuple[int, int, int] | None:
        """Why not leave it to SQLite: its auto-checkpoint runs only on a commit that finds 1,000 pages in
        the WAL, so a collection of a few hundred uploads lived in the ``-wal`` file alone, and a copy of the
        data dir without it (a common backup mistake) held nothing. PASSIVE never waits (it stops at the
        oldest reader's snapshot); TRUNCATE, at a clean stop, waits up to ``timeout_s`` for readers, then
        empties the WAL. Runs on a connection of its own, so it never waits for this process's transactions
        nor holds the store's lock."""
        try:
            con = sqlite3.connect(self.path, timeout=timeout_s, isolation_level=None)
            try:
                con.execute("PRAGMA synchronous=FULL")
                row = con.execute(f"PRAGMA wal_checkpoint({mode})").fetchone()
            finally:
                con.close()
        except sqlite3.Error as e:
            log.warning("checkpoint %s of %s failed: %s", mode, self.data_dir, e)
            # Not a reader in the way but the files themselves: a removed -wal gives "disk I/O error". (A full
            # disk is "database or disk is full": it passes, and writes work again once there is room.)
            why = files.changed() if files is not None else None
            if why is None and "i/o error" in str(e).lower():
                why = f"a checkpoint of the database failed ({e})"
            if why is not None:
                refuse(why)
            return None
        if row[0]:
            log.info(
                "checkpoint %s of %s: a reader holds %d of %d WAL frames", mode, self.data_dir, row[1] - row[2], row[1]
            )
        return int(row[0]), int(row[1]), int(row[2])

    def ref_high_water(self, db) -> int:
        row = db.execute(
            "SELECT MAX(COALESCE((SELECT seq FROM sqlite_sequence WHERE name='refs'), 0), "
            "COALESCE((SELECT MAX(id) FROM refs), 0))"
        ).fetchone()
        return int(row[0])

    def raise_counter(self, db, table: str, column: str, mark: int) -> None:
        """``AUTOINCREMENT``'s counter of ``table`` (its one such column) in ``sqlite_sequence``."""
        cur = db.execute("UPDATE sqlite_sequence SET seq = MAX(seq, ?) WHERE name = ?", (mark, table))
        if not cur.rowcount and mark:
            db.execute("INSERT INTO sqlite_sequence(name, seq) VALUES(?, ?)", (table, mark))

    def writer_lock(self) -> WorkerLock:
        """The data dir's lock file: every process of a SQLite collection shares that host."""
        return WorkerLock(self.data_dir)

    def dump(self, dest_dir: Path) -> list[str]:
        """SQLite's backup API copies a state of a database that other processes keep writing (a plain file
        copy of a WAL database does not); the names are read from the copy."""
        src = sqlite3.connect(self.path)
        dst = sqlite3.connect(Path(dest_dir) / DB_NAME)
        try:
            src.backup(dst)
            return [f"{sha}.{ext}" for sha, ext in dst.execute("SELECT sha256, image_ext FROM refs").fetchall()]
        finally:
            src.close()
            dst.close()

    def restore(self, source_dir: Path) -> None:
        src = sqlite3.connect(Path(source_dir) / DB_NAME)
        dst = sqlite3.connect(self.path)
        try:
            src.backup(dst)
        finally:
            src.close()
            dst.close()
