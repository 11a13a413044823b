"""The data directory: SQLite rows with their codes (the source of truth), stored images, a change log.

Why this shape: SQLite in WAL mode gives durable, atomic commits, so an accepted reference is a row that
survives a crash, and the codes live in that same row, so the FAISS indexes are only a cache. What keeps
that cache cheap to maintain is the change log: every change *of the index* (a reference encoded and
added, an indexed reference deleted) appends one row ``(version, ref_id, op)`` in the same transaction as
the change itself. The index version is the log's last version. A process holding the index at version
``v`` catches up by reading exactly the changes after ``v`` (with their codes, in one query), so the cost
of a change never depends on the collection's size. Accepting an upload (a ``pending`` row) is a change of
rows, not of the index, and appends nothing.

Every storage failure (unwritable folder, full disk, read-only database) surfaces as ``StorageUnavailable``
so callers answer "try again later" without losing what is already stored.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.engine.errors import IncompatibleArtifact
from app.engine.pipeline import Pipeline
from app.errors import StaleReindex, StorageUnavailable
from app.permissions import PRIVATE_FILE, create_private_file, private_dir

log = logging.getLogger("geoloc.store")

log = logging.getLogger("geoloc.store")

DB_NAME = "references.sqlite"
IMAGES = "images"
SCHEMA = """
CREATE TABLE IF NOT EXISTS refs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    sha256 TEXT NOT NULL UNIQUE,
    lat REAL NOT NULL,
    lon REAL NOT NULL,
    heading REAL,
    captured_at TEXT,
    label TEXT,
    source TEXT,
    image_ext TEXT,
    created_at TEXT NOT NULL,
    float_code BLOB,
    binary_code BLOB,
    status TEXT NOT NULL DEFAULT 'indexed',  -- pending (accepted, not encoded yet), indexed, failed
    error TEXT
);
CREATE INDEX IF NOT EXISTS refs_lat_lon ON refs(lat, lon);
CREATE INDEX IF NOT EXISTS refs_status ON refs(status);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    created_at TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS job_items (
    job_id TEXT NOT NULL REFERENCES jobs(id),
    position INTEGER NOT NULL,
    ref_id INTEGER NOT NULL,
    duplicate INTEGER NOT NULL DEFAULT 0,
    PRIMARY KEY (job_id, position)
);
-- The index's change log: one row per reference added to or deleted from the index.
CREATE TABLE IF NOT EXISTS changes (
    version INTEGER PRIMARY KEY AUTOINCREMENT,
    ref_id INTEGER NOT NULL,
    op TEXT NOT NULL CHECK (op IN ('add', 'delete', 'move'))
);
"""
#: Claims: pending rows a bulk run (``geoloc ingest``) encodes itself. A worker skips them until the lease
#: ends, so the rows of a run that crashed go back to the queue by themselves.
CLAIMS_SCHEMA = """
CREATE TABLE IF NOT EXISTS claims (
    ref_id INTEGER PRIMARY KEY,
    owner TEXT NOT NULL,
    expires REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS claims_owner ON claims(owner);
"""
#: Image files to remove, queued in the transaction that deletes the row naming them. A file is unlinked only
#: under the write lock and only while no row names it (``_unlink_unnamed``), and an add commits a row only
#: after checking, under the same lock, that its file is there (``insert_rows``): so whichever of an upload
#: and a delete of the same bytes commits last, across processes, a committed row always names a file. A
#: removal that fails (a read-only folder) stays queued and is retried by the writer process and by
#: ``geoloc check --repair``.
REMOVALS_SCHEMA = """
CREATE TABLE IF NOT EXISTS removals (
    name TEXT PRIMARY KEY,
    queued_at REAL NOT NULL
);
"""
# Index generations (a re-fit): the codes of the generation being built, one row per reference, until the
# switch copies them into ``refs`` in one transaction. Meta keys: ``generation`` (the number in use, 0 before
# any re-fit), ``pipeline`` (the fitted pipeline in use: ``models:<config>`` or ``pipelines/<config>-g<N>``
# under the data dir) and ``reindex_target`` (JSON: the generation being built, while a re-index runs).
NEXT_CODES = """
CREATE TABLE IF NOT EXISTS next_codes (
    ref_id INTEGER PRIMARY KEY,
    float_code BLOB,
    binary_code BLOB,
    error TEXT
);
"""
# After the switch the filled table is renamed ``switched_codes`` (O(1), in the switch transaction) and its
# codes win over those in ``refs`` until they are copied there in small transactions: the switch itself
# never holds the write lock for a time that grows with the collection.
GENERATIONS_SCHEMA = (
    NEXT_CODES
    + """
CREATE TABLE IF NOT EXISTS switched_codes (
    ref_id INTEGER PRIMARY KEY,
    float_code BLOB,
    binary_code BLOB,
    error TEXT
);
"""
)
#: A reference's codes of the generation in use: its row in ``switched_codes`` when there is one.
CODES = (
    "CASE WHEN s.ref_id IS NULL THEN r.float_code ELSE s.float_code END, "
    "CASE WHEN s.ref_id IS NULL THEN r.binary_code ELSE s.binary_code END"
)


@dataclass(frozen=True)
class Reference:
    id: int
    sha256: str
    lat: float
    lon: float
    heading: float | None
    captured_at: str | None
    label: str | None
    source: str | None
    created_at: str
    status: str = "indexed"
    error: str | None = None

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


_COLS = "id, sha256, lat, lon, heading, captured_at, label, source, created_at, status, error"


@dataclass
class NewReference:
    """One reference to store. With codes it is stored indexed (bulk loads of pre-encoded references);
    without, it is stored ``pending`` for the ingestion worker."""

    image: bytes
    ext: str
    lat: float
    lon: float
    heading: float | None = None
    captured_at: str | None = None
    label: str | None = None
    source: str | None = None
    float_code: np.ndarray | None = None
    binary_code: np.ndarray | None = None
    sha256: str = field(default="")

    def __post_init__(self):
        if not self.sha256:
            self.sha256 = sha256_of(self.image)

    @property
    def encoded(self) -> bool:
        return self.float_code is not None or self.binary_code is not None


@dataclass(frozen=True)
class Change:
    version: int
    ref_id: int
    op: str  # add | delete
    float_code: bytes | None
    binary_code: bytes | None


def sha256_of(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _blob(code: np.ndarray | None, dtype) -> bytes | None:
    return None if code is None else np.asarray(code, dtype).tobytes()


def _ids_json(ids) -> str:
    """Id lists of any length bind as one JSON parameter (``json_each``): SQLite caps bound variables."""
    return json.dumps([int(i) for i in ids])


_STORAGE_ERRNOS = {errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG, errno.EIO}


def is_storage_error(exc: BaseException) -> bool:
    if isinstance(exc, StorageUnavailable):
        return True
    if isinstance(exc, sqlite3.OperationalError):
        text = str(exc).lower()
        return any(
            s in text for s in ("readonly", "read-only", "disk", "full", "unable to open", "i/o", "locked", "busy")
        )
    if isinstance(exc, OSError):
        return exc.errno in _STORAGE_ERRNOS or isinstance(exc, NotADirectoryError | IsADirectoryError)
    return False


@contextmanager
def storage_guard(what: str) -> Iterator[None]:
    """Turn the storage's own failures into ``StorageUnavailable``; anything else passes through."""
    try:
        yield
    except (OSError, sqlite3.OperationalError, sqlite3.DatabaseError) as e:
        if isinstance(e, sqlite3.IntegrityError) or not (is_storage_error(e) or isinstance(e, sqlite3.DatabaseError)):
            raise
        raise StorageUnavailable(f"{what}: the data dir cannot be written right now ({e})") from e


#: Up to this many files a batch syncs each file; beyond, one ``syncfs`` of the images' file system.
SYNC_EACH_UP_TO = 8


def write_image_file(path: Path, data: bytes, sync: bool) -> None:
    """Write to a temporary name then rename, so a reader never sees half a file. ``sync``: flush this
    file's data now; otherwise the caller syncs the whole batch at once before committing its rows."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, PRIVATE_FILE)
    try:
        os.fchmod(fd, PRIVATE_FILE)  # the umask cannot widen it, and a stale temporary file is narrowed
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            if sync:
                os.fdatasync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _syncfs(folder: Path) -> None:
    """Flush every dirty page of the file system holding ``folder`` in one call (Linux ``syncfs``): a bulk
    batch of thousands of small files costs one flush instead of one per file (14 ms each on a busy disk)."""
    import ctypes

    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.syncfs(fd) != 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err))
    except AttributeError:  # no syncfs in this libc
        os.sync()
    finally:
        os.close(fd)


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class ReferenceStore:
    """One data directory bound to one fitted pipeline (its fingerprint is recorded on first use)."""

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
                self.db.executescript(SCHEMA)
                self.db.executescript(CLAIMS_SCHEMA)
                self.db.executescript(GENERATIONS_SCHEMA)
                self.db.executescript(REMOVALS_SCHEMA)
                self._ensure_database_id()

    def close(self) -> None:
        """Checkpoint (a writer's rows go into the main file, the WAL is emptied), then close."""
        if not self.read_only:
            self.checkpoint("TRUNCATE")
        self.db.close()

    # -- durability: the main file and the database's identity ------------------------------------------
    def _ensure_database_id(self) -> None:
        """Give the database its identity (a random id in meta) the first time it is opened, by this version
        or an older one that made none, and checkpoint it at once: the main file alone then names the
        database, so a copy of it without its ``-wal`` is recognised as this database at an older state."""
        if self.get_meta("database_id") is not None:
            return
        with self.transaction() as db:
            db.execute("INSERT OR IGNORE INTO meta(key, value) VALUES('database_id', ?)", (uuid.uuid4().hex,))
        if self.count(None):
            log.info("%s had no database id (made by an older version): it has one now", self.data_dir)
        self.checkpoint("PASSIVE")

    @property
    def database_id(self) -> str | None:
        """None only for a database made by an older version and opened read-only since."""
        return self.get_meta("database_id")

    def checkpoint(self, mode: str = "PASSIVE", timeout_s: float = 2.0) -> tuple[int, int, int] | None:
        """Copy the WAL's committed pages into the main file: (busy, WAL frames, frames checkpointed), or None
        when it could not run. Why not leave it to SQLite: its auto-checkpoint runs only on a commit that finds
        1,000 pages in the WAL, so a collection of a few hundred uploads lived in the ``-wal`` file alone, and
        a copy of the data dir without it (a common backup mistake) held nothing. PASSIVE never waits (it
        stops at the oldest reader's snapshot); TRUNCATE, at a clean stop, waits up to ``timeout_s`` for
        readers, then empties the WAL. Runs on a connection of its own, so it never waits for this process's
        transactions nor holds the store's lock."""
        if self.read_only:
            return None
        try:
            con = sqlite3.connect(self.data_dir / DB_NAME, timeout=timeout_s, isolation_level=None)
            try:
                con.execute("PRAGMA synchronous=FULL")
                row = con.execute(f"PRAGMA wal_checkpoint({mode})").fetchone()
            finally:
                con.close()
        except sqlite3.Error as e:
            log.warning("checkpoint %s of %s failed: %s", mode, self.data_dir, e)
            return None
        if row[0]:
            log.info(
                "checkpoint %s of %s: a reader holds %d of %d WAL frames", mode, self.data_dir, row[1] - row[2], row[1]
            )
        return int(row[0]), int(row[1]), int(row[2])

    def ref_high_water(self) -> int:
        """The largest reference id ever handed out (AUTOINCREMENT's counter, or a larger row id)."""
        row = self.db.execute(
            "SELECT MAX(COALESCE((SELECT seq FROM sqlite_sequence WHERE name='refs'), 0), "
            "COALESCE((SELECT MAX(id) FROM refs), 0))"
        ).fetchone()
        return int(row[0])

    def binding(self, version: int) -> dict:
        """What binds a snapshot of the index at ``version`` to this database: its id, the reference id
        high-water mark, and the change log's entry at ``version`` with its image's sha256 (two databases
        that diverged after a common past disagree there)."""
        with self.read_snapshot():
            return {
                "database_id": self.database_id,
                "ref_high_water": self.ref_high_water(),
                "last_change": self._change_at(version),
            }

    def _change_at(self, version: int) -> list | None:
        """The change log's entry at ``version``: [ref_id, op, the reference's sha256 (None once deleted)]."""
        row = self.db.execute(
            "SELECT c.ref_id, c.op, r.sha256 FROM changes c LEFT JOIN refs r ON r.id = c.ref_id WHERE c.version=?",
            (version,),
        ).fetchone()
        return list(row) if row else None

    def binding_state(self, version: int) -> tuple[str | None, int, list | None]:
        """(database id, index version, change-log entry at ``version``) read together, to check a snapshot."""
        with self.read_snapshot() as db:
            head = int(db.execute("SELECT COALESCE(MAX(version), 0) FROM changes").fetchone()[0])
            return self.database_id, head, self._change_at(version)

    def retire_snapshot(self, manifest: dict) -> None:
        """A snapshot was refused: raise AUTOINCREMENT's counters past what it knew, so the ids of references
        it indexes (lost from this database) are never handed out again, and the change log never again
        reaches its version with other entries (the refused snapshot can never match later)."""
        if self.read_only:
            return
        marks = {"refs": int(manifest.get("ref_high_water") or 0), "changes": int(manifest.get("version") or 0)}
        with self.transaction() as db:
            for table, mark in marks.items():
                cur = db.execute("UPDATE sqlite_sequence SET seq = MAX(seq, ?) WHERE name = ?", (mark, table))
                if not cur.rowcount and mark:
                    db.execute("INSERT INTO sqlite_sequence(name, seq) VALUES(?, ?)", (table, mark))

    @property
    def images_dir(self) -> Path:
        return self.data_dir / IMAGES

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

    def bind(self, pipeline: Pipeline) -> None:
        """Record which fitted pipeline encoded this collection; refuse a different one."""
        fp = self.get_meta("fingerprint")
        if fp is not None and fp != pipeline.fingerprint and self.count(None) > 0:
            raise IncompatibleArtifact(
                f"{self.data_dir} holds codes from pipeline {fp}, not {pipeline.fingerprint}: use the models dir "
                "and --config the collection was built with, or start a new --data-dir"
            )
        if not self.read_only and fp != pipeline.fingerprint:
            self.set_meta("fingerprint", pipeline.fingerprint)
            self.set_meta("config", pipeline.config.name)

    @property
    def version(self) -> int:
        """The index version: the change log's last entry. Pending uploads do not move it. Read under the
        store's lock: on the connection this process shares between threads, a read inside another thread's
        open write transaction would see changes that may yet roll back."""
        with self._lock:
            return int(self.db.execute("SELECT COALESCE(MAX(version), 0) FROM changes").fetchone()[0])

    # -- adding ---------------------------------------------------------------------------------------
    def image_path_for(self, sha: str, ext: str) -> Path:
        return self.images_dir / f"{sha}.{ext}"

    def existing_ids(self, shas: Sequence[str]) -> dict[str, int]:
        rows = self.db.execute(
            "SELECT sha256, id FROM refs WHERE sha256 IN (SELECT value FROM json_each(?))", (json.dumps(list(shas)),)
        ).fetchall()
        return {s: i for s, i in rows}

    def write_images(self, items: Sequence[NewReference], skip: set[str] = frozenset()) -> None:
        """Images first, then their data and the folder synced once per batch: a row is committed only after
        the file it names (and the folder entry) is on disk."""
        todo = [it for it in items if it.sha256 not in skip]
        each = len(todo) <= SYNC_EACH_UP_TO
        with storage_guard("writing images"):
            written = False
            for it in todo:
                path = self.image_path_for(it.sha256, it.ext)
                if not path.exists():
                    write_image_file(path, it.image, sync=each)
                    written = True
            if written:
                if not each:
                    _syncfs(self.images_dir)
                fsync_dir(self.images_dir)

    def insert_rows(
        self, items: Sequence[NewReference], job: bool = False
    ) -> tuple[list[tuple[int, bool]], str | None]:
        """Insert rows in one transaction; identical bytes (already stored, or racing in from another process
        at this very moment) come back as the existing id with ``created`` False. Encoded items are stored
        indexed and logged as index changes in the same transaction. Each created row's file is checked (and
        written again if a delete removed it meanwhile) before the commit: see ``REMOVALS_SCHEMA``."""
        out: list[tuple[int, bool]] = []
        job_id = uuid.uuid4().hex if job else None
        now = _now()
        created: list[NewReference] = []
        with self.transaction() as db:
            for it in items:
                row = db.execute(
                    "INSERT INTO refs(sha256, lat, lon, heading, captured_at, label, source, image_ext, created_at, "
                    "float_code, binary_code, status) VALUES(?,?,?,?,?,?,?,?,?,?,?,?) "
                    "ON CONFLICT(sha256) DO NOTHING RETURNING id",
                    (
                        it.sha256,
                        it.lat,
                        it.lon,
                        it.heading,
                        it.captured_at,
                        it.label,
                        it.source,
                        it.ext,
                        now,
                        _blob(it.float_code, np.float32),
                        _blob(it.binary_code, np.uint8),
                        "indexed" if it.encoded else "pending",
                    ),
                ).fetchone()
                if row is not None:
                    out.append((int(row[0]), True))
                    created.append(it)
                    if it.encoded:
                        db.execute("INSERT INTO changes(ref_id, op) VALUES(?, 'add')", (int(row[0]),))
                else:
                    existing = db.execute("SELECT id FROM refs WHERE sha256=?", (it.sha256,)).fetchone()
                    out.append((int(existing[0]), False))
            self._files_for(db, created)
            if job_id is not None:
                db.execute("INSERT INTO jobs(id, created_at) VALUES(?, ?)", (job_id, now))
                db.executemany(
                    "INSERT INTO job_items(job_id, position, ref_id, duplicate) VALUES(?,?,?,?)",
                    [(job_id, n, ref_id, int(not created)) for n, (ref_id, created) in enumerate(out)],
                )
        return out, job_id

    def add_many(self, items: Sequence[NewReference], job: bool = False) -> tuple[list[tuple[int, bool]], str | None]:
        """The bulk path: images written and synced, then every row in one transaction (with its job).
        Returns ``[(id, created)]`` in order, and the job id when ``job``."""
        known = self.existing_ids([it.sha256 for it in items])
        self.write_images(items, skip=set(known))
        return self.insert_rows(items, job)

    def add(self, image: bytes, ext: str, lat: float, lon: float, float_code=None, binary_code=None, **meta):
        """One reference (tests and small tools); see ``add_many``."""
        ((ref_id, created),), _ = self.add_many(
            [NewReference(image, ext, lat, lon, float_code=float_code, binary_code=binary_code, **meta)]
        )
        return ref_id, created

    def _files_for(self, db: sqlite3.Connection, created: Sequence[NewReference]) -> None:
        """Inside an add's write transaction: every created row's file is on disk when it commits. The files
        were written (or found) before the transaction, so this is one ``stat`` per row; only a file that a
        delete (or the orphan sweep) removed after that is written again here, under the lock. Removals
        queued for these names are dropped: the names are in use again."""
        if not created:
            return
        folder = str(self.images_dir)
        names = [f"{it.sha256}.{it.ext}" for it in created]
        gone = [(it, name) for it, name in zip(created, names, strict=True) if not os.path.exists(f"{folder}/{name}")]
        for it, name in gone:
            write_image_file(self.images_dir / name, it.image, sync=True)
        if gone:
            fsync_dir(self.images_dir)
        db.execute("DELETE FROM removals WHERE name IN (SELECT value FROM json_each(?))", (json.dumps(names),))

    # -- deleting -------------------------------------------------------------------------------------
    def delete(self, ref_id: int) -> str | None:
        """Delete the row (an indexed one is logged so every process drops it from its index) and queue its
        file for removal in the same transaction, then remove the file. Returns None when there is no such
        reference, ``"removed"``, or ``"queued"`` when the file could not be removed now: the reference is
        gone all the same, and the removal is retried (``remove_queued``) by the writer process and by
        ``geoloc check --repair``."""
        with self.transaction() as db:
            row = db.execute("SELECT sha256, image_ext, status FROM refs WHERE id=?", (ref_id,)).fetchone()
            if row is None:
                return None
            db.execute("DELETE FROM refs WHERE id=?", (ref_id,))
            if row[2] == "indexed":
                db.execute("INSERT INTO changes(ref_id, op) VALUES(?, 'delete')", (ref_id,))
            name = self.image_path_for(row[0], row[1]).name
            db.execute(
                "INSERT INTO removals(name, queued_at) VALUES(?, ?) ON CONFLICT(name) DO NOTHING", (name, time.time())
            )
        try:
            _, failed = self.remove_queued([name])
        except StorageUnavailable as e:
            log.warning("reference %d deleted; removing its image is queued (%s)", ref_id, e)
            return "queued"
        return "queued" if failed else "removed"

    def queued_removals(self) -> list[str]:
        """The file names still queued for removal (an empty list on a data dir from before the queue)."""
        try:
            with self._lock:  # not inside another thread's open transaction on this shared connection
                return [r[0] for r in self.db.execute("SELECT name FROM removals ORDER BY queued_at").fetchall()]
        except sqlite3.OperationalError:  # a read-only open of a data dir without the table
            return []

    def remove_queued(self, names: Sequence[str] | None = None, limit: int = 1000) -> tuple[list[str], list[str]]:
        """Remove queued files (those in ``names``, or up to ``limit`` of the oldest): each is unlinked under
        the write lock unless a row names it again (an upload of the same bytes since), and leaves the queue
        unless its unlink failed. Returns (removed, failed)."""
        with self.transaction() as db:
            if names is None:
                rows = db.execute("SELECT name FROM removals ORDER BY queued_at LIMIT ?", (limit,)).fetchall()
            else:
                rows = db.execute(
                    "SELECT name FROM removals WHERE name IN (SELECT value FROM json_each(?))",
                    (json.dumps(list(names)),),
                ).fetchall()
            queued = [r[0] for r in rows]
            removed, failed = self._unlink_unnamed(db, queued)
            db.execute(
                "DELETE FROM removals WHERE name IN (SELECT value FROM json_each(?))",
                (json.dumps(sorted(set(queued) - set(failed))),),
            )
        return removed, failed

    def remove_unnamed(self, names: Sequence[str]) -> tuple[list[str], list[str]]:
        """Unlink the image files among ``names`` that no row names (orphans), under the write lock so that
        an add of the same bytes either commits first (and its file is kept) or re-writes the file in its
        own transaction. Returns (removed, failed)."""
        with self.transaction() as db:
            return self._unlink_unnamed(db, names)

    def _unlink_unnamed(self, db: sqlite3.Connection, names: Sequence[str]) -> tuple[list[str], list[str]]:
        """Inside a write transaction: unlink each of ``names`` that no row names. A file that cannot be
        unlinked is reported, not raised: the caller keeps it queued."""
        named = self.named_files(names, db)
        removed: list[str] = []
        failed: list[str] = []
        for name in names:
            if name in named:
                continue
            try:
                (self.images_dir / name).unlink(missing_ok=True)
                removed.append(name)
            except OSError as e:
                log.warning("cannot remove %s now: %s", self.images_dir / name, e)
                failed.append(name)
        return removed, failed

    def named_files(self, names: Sequence[str], db: sqlite3.Connection | None = None) -> set[str]:
        """Those of ``names`` (image file names) that a row names: one lookup of the sha256 index each."""
        if not names:
            return set()
        shas = json.dumps([n.split(".", 1)[0] for n in names])
        conn = db or self.db
        with self._lock:
            rows = conn.execute(
                "SELECT sha256, image_ext FROM refs WHERE sha256 IN (SELECT value FROM json_each(?))", (shas,)
            ).fetchall()
        return {f"{sha}.{ext}" for sha, ext in rows} & set(names)

    # -- editing --------------------------------------------------------------------------------------
    EDITABLE = ("lat", "lon", "heading", "label", "captured_at")

    def update(self, ref_id: int, fields: dict) -> Reference | None:
        """Change metadata in one transaction; a position change is logged ('move') like any change of where
        a reference is, so every process that follows the log learns of it. None: no such reference."""
        unknown = set(fields) - set(self.EDITABLE)
        if unknown:
            raise ValueError(f"not editable: {sorted(unknown)}")
        with self.transaction() as db:
            row = db.execute("SELECT lat, lon FROM refs WHERE id=?", (ref_id,)).fetchone()
            if row is None:
                return None
            if fields:
                sets = ", ".join(f"{k}=?" for k in fields)
                db.execute(f"UPDATE refs SET {sets} WHERE id=?", (*fields.values(), ref_id))
            if (fields.get("lat", row[0]), fields.get("lon", row[1])) != tuple(row):
                db.execute("INSERT INTO changes(ref_id, op) VALUES(?, 'move')", (ref_id,))
        return self.get(ref_id)

    # -- reading --------------------------------------------------------------------------------------
    def get(self, ref_id: int) -> Reference | None:
        row = self.db.execute(f"SELECT {_COLS} FROM refs WHERE id=?", (ref_id,)).fetchone()
        return Reference(*row) if row else None

    def get_many(self, ids: Sequence[int]) -> dict[int, Reference]:
        """Rows of many ids in one read (the candidates of a search)."""
        if len(ids) == 0:
            return {}
        rows = self.db.execute(
            f"SELECT {_COLS} FROM refs WHERE id IN (SELECT value FROM json_each(?))", (_ids_json(ids),)
        ).fetchall()
        return {r[0]: Reference(*r) for r in rows}

    def image_path(self, ref_id: int) -> Path | None:
        """Where the reference's image is (or should be); None when there is no such reference."""
        row = self.db.execute("SELECT sha256, image_ext FROM refs WHERE id=?", (ref_id,)).fetchone()
        return self.image_path_for(row[0], row[1]) if row else None

    def list(
        self, offset: int = 0, limit: int = 50, bbox: tuple[float, float, float, float] | None = None
    ) -> tuple[list[Reference], int]:
        where, args = "", []
        if bbox is not None:
            min_lon, min_lat, max_lon, max_lat = bbox
            where, args = "WHERE lat BETWEEN ? AND ? AND lon BETWEEN ? AND ?", [min_lat, max_lat, min_lon, max_lon]
        total = self.db.execute(f"SELECT COUNT(*) FROM refs {where}", args).fetchone()[0]
        rows = self.db.execute(
            f"SELECT {_COLS} FROM refs {where} ORDER BY id LIMIT ? OFFSET ?", [*args, limit, offset]
        ).fetchall()
        return [Reference(*r) for r in rows], total

    def in_bbox(self, bbox: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, lats, lons) of indexed references inside a bbox, in one read."""
        min_lon, min_lat, max_lon, max_lat = bbox
        rows = self.db.execute(
            "SELECT id, lat, lon FROM refs WHERE lat BETWEEN ? AND ? AND lon BETWEEN ? AND ? AND status='indexed'",
            (min_lat, max_lat, min_lon, max_lon),
        ).fetchall()
        if not rows:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
        a = np.array(rows, np.float64)
        return a[:, 0].astype(np.int64), a[:, 1], a[:, 2]

    def ids_in_bbox(self, bbox: tuple[float, float, float, float]) -> np.ndarray:
        return self.in_bbox(bbox)[0]

    def count(self, status: str | None = "indexed") -> int:
        """References in the index (by default), or of another status, or all (None)."""
        if status is None:
            return self.db.execute("SELECT COUNT(*) FROM refs").fetchone()[0]
        return self.db.execute("SELECT COUNT(*) FROM refs WHERE status=?", (status,)).fetchone()[0]

    def positions(self, ids) -> tuple[np.ndarray, np.ndarray]:
        """(lats, lons) in the order of ``ids`` (NaN where unknown), for id lists of any length."""
        ids = [int(i) for i in ids]
        if not ids:
            return np.zeros(0), np.zeros(0)
        found = {
            r[0]: (r[1], r[2])
            for r in self.db.execute(
                "SELECT id, lat, lon FROM refs WHERE id IN (SELECT value FROM json_each(?))", (_ids_json(ids),)
            )
        }
        pos = np.array([found.get(i, (np.nan, np.nan)) for i in ids], np.float64)
        return pos[:, 0], pos[:, 1]

    # -- the ingestion queue: pending rows are the durable queue ---------------------------------------
    def pending(self, limit: int, after: int = 0) -> list[tuple[int, Path]]:
        """The next pending rows in id order, except those another run claimed and whose lease still runs."""
        rows = self.db.execute(
            "SELECT r.id, r.sha256, r.image_ext FROM refs r LEFT JOIN claims c ON c.ref_id = r.id "
            "WHERE r.status='pending' AND r.id > ? AND (c.expires IS NULL OR c.expires <= ?) ORDER BY r.id LIMIT ?",
            (after, time.time(), limit),
        ).fetchall()
        return [(r[0], self.image_path_for(r[1], r[2])) for r in rows]

    def claim(self, ids: Sequence[int], owner: str, lease_s: float) -> None:
        """Claim rows for ``owner`` for ``lease_s`` seconds (one statement for the whole list); a claim held
        by another owner is taken over only once its lease has ended."""
        with self.transaction() as db:
            db.execute(
                "INSERT INTO claims(ref_id, owner, expires) SELECT value, ?, ? FROM json_each(?) WHERE true "
                "ON CONFLICT(ref_id) DO UPDATE SET owner=excluded.owner, expires=excluded.expires "
                "WHERE claims.owner = excluded.owner OR claims.expires <= ?",
                (owner, time.time() + lease_s, _ids_json(ids), time.time()),
            )

    def release(self, owner: str, ids: Sequence[int] | None = None) -> None:
        """Drop ``owner``'s claims on ``ids`` (all of them when None): done rows, or the end of a run."""
        with self.transaction() as db:
            if ids is None:
                db.execute("DELETE FROM claims WHERE owner=?", (owner,))
            else:
                db.execute(
                    "DELETE FROM claims WHERE owner=? AND ref_id IN (SELECT value FROM json_each(?))",
                    (owner, _ids_json(ids)),
                )

    def complete(
        self,
        results: Sequence[tuple[int, np.ndarray | None, np.ndarray | None, str | None]],
        fingerprint: str | None = None,
    ) -> list[int]:
        """Record encoded codes (or an error) for pending rows, in one transaction, logging each newly indexed
        row; return those ids. Rows deleted meanwhile are skipped, and re-running a batch changes nothing:
        completing is idempotent, so a worker killed anywhere can simply start again. ``fingerprint``: the
        pipeline that encoded the batch; when a re-fit has switched the data dir to another one meanwhile,
        nothing is recorded and the rows stay pending (to be encoded again by the new pipeline)."""
        done = []
        with self.transaction() as db:
            if fingerprint is not None and not self._fingerprint_is(db, fingerprint):
                return []
            for ref_id, fcode, bcode, error in results:
                if error is not None:
                    db.execute(
                        "UPDATE refs SET status='failed', error=? WHERE id=? AND status='pending'", (error, ref_id)
                    )
                    continue
                cur = db.execute(
                    "UPDATE refs SET float_code=?, binary_code=?, status='indexed' WHERE id=? AND status='pending'",
                    (_blob(fcode, np.float32), _blob(bcode, np.uint8), ref_id),
                )
                if cur.rowcount:
                    db.execute("INSERT INTO changes(ref_id, op) VALUES(?, 'add')", (ref_id,))
                    done.append(ref_id)
        return done

    def job(self, job_id: str) -> dict | None:
        row = self.db.execute("SELECT created_at FROM jobs WHERE id=?", (job_id,)).fetchone()
        if row is None:
            return None
        items = self.db.execute(
            "SELECT j.position, j.ref_id, j.duplicate, r.status, r.error FROM job_items j "
            "LEFT JOIN refs r ON r.id = j.ref_id WHERE j.job_id=? ORDER BY j.position",
            (job_id,),
        ).fetchall()
        out = [
            {"reference_id": i[1], "duplicate": bool(i[2]), "status": i[3] or "deleted", "error": i[4]} for i in items
        ]
        counts = {s: sum(1 for o in out if o["status"] == s) for s in ("pending", "indexed", "failed", "deleted")}
        status = (
            "queued"
            if counts["pending"] == len(out)
            else "running"
            if counts["pending"]
            else ("failed" if counts["failed"] == len(out) else "done")
        )
        return {"id": job_id, "created_at": row[0], "status": status, "total": len(out), **counts, "items": out}

    # -- what the index is built from -----------------------------------------------------------------
    def changes_since(self, version: int) -> list[Change]:
        """The index changes after ``version``, oldest first, each add with its codes (NULL when the row was
        deleted since: a later delete entry follows). Under the lock, like ``version``."""
        with self._lock:
            rows = self.db.execute(
                f"SELECT c.version, c.ref_id, c.op, {CODES} FROM changes c "
                "LEFT JOIN refs r ON r.id = c.ref_id AND r.status = 'indexed' AND c.op = 'add' "
                "LEFT JOIN switched_codes s ON s.ref_id = r.id "
                "WHERE c.version > ? ORDER BY c.version",
                (version,),
            ).fetchall()
        return [Change(*r) for r in rows]

    def all_codes(self) -> tuple[int, np.ndarray, list[bytes | None], list[bytes | None]]:
        """Every indexed row's codes and the index version they make up, read in one consistent snapshot."""
        with self.read_snapshot() as db:
            version = int(db.execute("SELECT COALESCE(MAX(version), 0) FROM changes").fetchone()[0])
            rows = db.execute(
                f"SELECT r.id, {CODES} FROM refs r LEFT JOIN switched_codes s ON s.ref_id = r.id "
                "WHERE r.status='indexed' ORDER BY r.id"
            ).fetchall()
        return version, np.array([r[0] for r in rows], np.int64), [r[1] for r in rows], [r[2] for r in rows]

    def indexed_ids(self) -> np.ndarray:
        rows = self.db.execute("SELECT id FROM refs WHERE status='indexed' ORDER BY id").fetchall()
        return np.array([r[0] for r in rows], np.int64)

    # -- index generations (a re-fit re-encodes every reference, then switches in one transaction) -------
    def _fingerprint_is(self, db: sqlite3.Connection, fingerprint: str) -> bool:
        row = db.execute("SELECT value FROM meta WHERE key='fingerprint'").fetchone()
        return row is None or row[0] == fingerprint

    def head(self) -> tuple[int, int]:
        """(index version, generation) in one read: what every process compares before each search."""
        with self._lock:
            row = self.db.execute(
                "SELECT (SELECT COALESCE(MAX(version), 0) FROM changes), "
                "(SELECT value FROM meta WHERE key='generation')"
            ).fetchone()
        return int(row[0]), int(row[1] or 0)

    def generation_state(self) -> tuple[int, str | None, str | None]:
        """(generation, pipeline, config) read together, so a process never pairs one generation's number
        with another's pipeline."""
        with self._lock:
            rows = dict(
                self.db.execute(
                    "SELECT key, value FROM meta WHERE key IN ('generation', 'pipeline', 'config')"
                ).fetchall()
            )
        return int(rows.get("generation") or 0), rows.get("pipeline"), rows.get("config")

    def generation_codes(self) -> tuple[int, int, np.ndarray, list[bytes | None], list[bytes | None]]:
        """``all_codes`` plus the generation they belong to, read in one consistent snapshot."""
        with self.read_snapshot() as db:
            gen = db.execute("SELECT value FROM meta WHERE key='generation'").fetchone()
            version = int(db.execute("SELECT COALESCE(MAX(version), 0) FROM changes").fetchone()[0])
            rows = db.execute(
                f"SELECT r.id, {CODES} FROM refs r LEFT JOIN switched_codes s ON s.ref_id = r.id "
                "WHERE r.status='indexed' ORDER BY r.id"
            ).fetchall()
        ids = np.array([r[0] for r in rows], np.int64)
        return int(gen[0]) if gen else 0, version, ids, [r[1] for r in rows], [r[2] for r in rows]

    def reindex_target(self) -> dict | None:
        value = self.get_meta("reindex_target")
        return json.loads(value) if value else None

    def start_reindex(self, target: dict) -> int:
        """Make ``target`` the generation being built. The same target again continues (its codes so far are
        kept); another one starts over. Returns how many references already have their new codes."""
        value = json.dumps(target, sort_keys=True)
        while self.migrate_switched():  # the previous switch's codes first (an interrupted refit)
            pass
        with self.transaction() as db:
            row = db.execute("SELECT value FROM meta WHERE key='reindex_target'").fetchone()
            if row is None or row[0] != value:
                db.execute("DELETE FROM next_codes")
                db.execute(
                    "INSERT INTO meta(key, value) VALUES('reindex_target', ?) "
                    "ON CONFLICT(key) DO UPDATE SET value=excluded.value",
                    (value,),
                )
            return int(db.execute("SELECT COUNT(*) FROM next_codes").fetchone()[0])

    def abandon_reindex(self) -> None:
        with self.transaction() as db:
            db.execute("DELETE FROM next_codes")
            db.execute("DELETE FROM meta WHERE key='reindex_target'")

    def reindex_todo(self, limit: int, after: int = 0) -> list[tuple[int, Path]]:
        """Indexed references after ``after`` (by id) that have no code of the new generation yet."""
        rows = self.db.execute(
            "SELECT r.id, r.sha256, r.image_ext FROM refs r LEFT JOIN next_codes n ON n.ref_id = r.id "
            "WHERE r.status='indexed' AND r.id > ? AND n.ref_id IS NULL ORDER BY r.id LIMIT ?",
            (after, limit),
        ).fetchall()
        return [(r[0], self.image_path_for(r[1], r[2])) for r in rows]

    def put_next_codes(
        self, target: dict, results: Sequence[tuple[int, np.ndarray | None, np.ndarray | None, str | None]]
    ) -> int:
        """Record a batch of the new generation's codes (or why a reference could not be encoded) in one
        transaction. Refused (``StaleReindex``) when another re-index has taken over the data dir."""
        value = json.dumps(target, sort_keys=True)
        with self.transaction() as db:
            row = db.execute("SELECT value FROM meta WHERE key='reindex_target'").fetchone()
            if row is None or row[0] != value:
                raise StaleReindex("another re-index took over this data dir (or it was switched already)")
            db.executemany(
                "INSERT OR REPLACE INTO next_codes(ref_id, float_code, binary_code, error) VALUES(?,?,?,?)",
                [(i, _blob(f, np.float32), _blob(b, np.uint8), e) for i, f, b, e in results],
            )
        return len(results)

    def reindex_missing(self) -> int:
        """Indexed references still without a code of the new generation."""
        return int(
            self.db.execute(
                "SELECT COUNT(*) FROM refs r LEFT JOIN next_codes n ON n.ref_id = r.id "
                "WHERE r.status='indexed' AND n.ref_id IS NULL"
            ).fetchone()[0]
        )

    def switch_generation(self, target: dict, fingerprint: str, config: str) -> int | None:
        """Switch to ``target`` in one write transaction: re-check that every indexed reference has its new
        code (uploads indexed meanwhile may not: then nothing changes and None is returned), mark failed the
        references the new pipeline could not encode, rename ``next_codes`` to ``switched_codes`` (whose
        codes every reader takes over those in ``refs``: constant time, whatever the collection's size) and
        record the pipeline, generation and fingerprint. ``migrate_switched`` then copies the codes into
        ``refs`` in short transactions. Returns the new generation."""
        value = json.dumps(target, sort_keys=True)
        with self.transaction() as db:
            row = db.execute("SELECT value FROM meta WHERE key='reindex_target'").fetchone()
            if row is None or row[0] != value:
                raise StaleReindex("another re-index took over this data dir (or it was switched already)")
            missing = db.execute(
                "SELECT COUNT(*) FROM refs r LEFT JOIN next_codes n ON n.ref_id = r.id "
                "WHERE r.status='indexed' AND n.ref_id IS NULL"
            ).fetchone()[0]
            if missing:
                return None
            if db.execute("SELECT 1 FROM switched_codes LIMIT 1").fetchone():
                raise StaleReindex("the previous switch's codes are still being copied: run `geoloc refit` again")
            db.execute(
                "UPDATE refs SET status='failed', error='re-index: ' || n.error, float_code=NULL, binary_code=NULL "
                "FROM (SELECT ref_id, error FROM next_codes WHERE error IS NOT NULL) n "
                "WHERE refs.id = n.ref_id AND refs.status='indexed'"
            )
            db.execute("DROP TABLE switched_codes")
            db.execute("ALTER TABLE next_codes RENAME TO switched_codes")
            db.execute(NEXT_CODES.strip().rstrip(";"))
            meta = {
                "generation": str(int(target["generation"])),
                "pipeline": str(target["pipeline"]),
                "fingerprint": fingerprint,
                "config": config,
            }
            db.executemany(
                "INSERT INTO meta(key, value) VALUES(?, ?) ON CONFLICT(key) DO UPDATE SET value=excluded.value",
                list(meta.items()),
            )
            db.execute("DELETE FROM meta WHERE key='reindex_target'")
        return int(target["generation"])

    def migrate_switched(self, batch: int = 5000) -> int:
        """Copy up to ``batch`` of the last switch's codes into ``refs`` in one short transaction (readers see
        the same codes before and after); returns how many rows it handled (0: nothing left)."""
        with self.transaction() as db:
            rows = db.execute(
                "SELECT ref_id, float_code, binary_code FROM switched_codes ORDER BY ref_id LIMIT ?", (batch,)
            ).fetchall()
            if not rows:
                return 0
            db.executemany(
                "UPDATE refs SET float_code=?, binary_code=? WHERE id=? AND status='indexed'",
                [(f, b, i) for i, f, b in rows],
            )
            db.execute("DELETE FROM switched_codes WHERE ref_id <= ?", (rows[-1][0],))
        return len(rows)
