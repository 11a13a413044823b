"""The data directory: SQLite rows with their codes (the source of truth), stored images, a change log.

Why this shape: SQLite in WAL mode gives durable, atomic commits, so an accepted reference is a row that
survives a crash, and the codes live in that same row, so the FAISS indexes are only a cache. What keeps
that cache cheap to maintain is the change log (``app.storage.changes``): every change *of the index*
appends one row in the same transaction as the change itself, so the cost of a change never depends on the
collection's size. Accepting an upload (a ``pending`` row) is a change of rows, not of the index, and
appends nothing.

``ReferenceStore`` is composed of the storage's parts, each holding the store's one ``Database`` (one
connection, one lock, one backend) and owning its tables: this module holds the rows and their images;
``queue`` the pending rows, claims and jobs; ``changes`` the change log; ``generations`` a re-fit's codes;
``identity`` the database's id and checkpoints; ``removals`` the image files to remove; ``maintenance``
what a check reads. Why one database under them: an add writes rows, the change log, a job and the removal
queue in one transaction on one connection under one lock. The store forwards the parts' methods, so
callers keep ``store.pending(...)``.

Every storage failure (unwritable folder, full disk, read-only database) surfaces as ``StorageUnavailable``
so callers answer "try again later" without losing what is already stored.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import sqlite3
import time
import uuid
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.engine.errors import IncompatibleArtifact
from app.errors import StorageUnavailable
from app.storage.backend import StorageBackend
from app.storage.changes import ChangeLog
from app.storage.database import Database, blob, ids_json
from app.storage.errors import storage_guard
from app.storage.files import SYNC_EACH_UP_TO, fsync_dir, sha256_of, syncfs, write_image_file
from app.storage.generations import Generations
from app.storage.identity import Identity
from app.storage.maintenance import Maintenance
from app.storage.queue import Queue
from app.storage.removals import Removals
from app.storage.sqlite import SqliteBackend

if TYPE_CHECKING:
    from app.engine.pipeline import Pipeline

log = logging.getLogger("geoloc.store")


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


_MAX_ID = 2**63 - 1  # the largest id SQLite and PostgreSQL's BIGINT hold


@dataclass(frozen=True)
class KeysetPage:
    """References in id order, and the ids to ask for the next and previous pages (None: no more)."""

    items: list[Reference]
    next_after: int | None
    prev_before: int | None


def _bbox_where(bbox: tuple[float, float, float, float] | None) -> tuple[str, list]:
    if bbox is None:
        return "", []
    min_lon, min_lat, max_lon, max_lat = bbox
    return "WHERE lat BETWEEN ? AND ? AND lon BETWEEN ? AND ?", [min_lat, max_lat, min_lon, max_lon]


#: The columns an add writes, in the order of ``_row``.
_INSERT_COLS = (
    "sha256", "lat", "lon", "heading", "captured_at", "label", "source", "image_ext", "created_at",
    "float_code", "binary_code", "status",
)  # fmt: skip
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


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _row(it: NewReference, now: str) -> tuple:
    """``it`` as the values of ``_INSERT_COLS``."""
    return (
        it.sha256, it.lat, it.lon, it.heading, it.captured_at, it.label, it.source, it.ext, now,
        blob(it.float_code, np.float32), blob(it.binary_code, np.uint8), "indexed" if it.encoded else "pending",
    )  # fmt: skip


def _forward(part: str, method: Callable) -> Callable:
    """``store.name(...)`` calls ``store.<part>.name(...)`` (same signature and docstring)."""

    @functools.wraps(method)
    def call(self: ReferenceStore, *args: Any, **kwargs: Any) -> Any:
        return method(getattr(self, part), *args, **kwargs)

    return call


class ReferenceStore:
    """One data directory (or database) bound to one fitted pipeline (its fingerprint is recorded on first
    use). ``backend``: the one the process made from its settings (``Settings.backend``); None: the embedded
    default, SQLite in ``data_dir`` (never the environment: that is read once, at the entry point)."""

    def __init__(self, data_dir: Path, read_only: bool = False, backend: StorageBackend | None = None):
        self.database = Database(backend or SqliteBackend(data_dir), read_only)
        self.changes = ChangeLog(self.database)
        self.queue = Queue(self.database, self.changes)
        self.generations = Generations(self.database)
        self.identity = Identity(self.database)
        self.removals = Removals(self.database)
        self.maintenance = Maintenance(self.database)
        if not read_only:
            with storage_guard("opening the data dir"):
                self.identity.ensure_id()

    def close(self) -> None:
        """Checkpoint (a writer's rows go into the main file, the WAL is emptied), then close."""
        if not self.read_only:
            self.checkpoint("TRUNCATE")
        self.database.close()

    # -- the database --------------------------------------------------------------------------------
    @property
    def backend(self) -> StorageBackend:
        return self.database.backend

    @property
    def engine(self) -> str:
        """The backend's name (``sqlite`` or ``postgres``): what /health and a backup report."""
        return self.database.backend.name

    @property
    def db(self) -> Any:
        """The connection (its queries are the parts'; tools and tests read through it)."""
        return self.database.db

    @property
    def data_dir(self) -> Path:
        return self.database.data_dir

    @property
    def read_only(self) -> bool:
        return self.database.read_only

    @property
    def images_dir(self) -> Path:
        return self.database.images_dir

    @property
    def snapshots_dir(self) -> Path:
        return self.database.snapshots_dir

    @property
    def write_refusal(self) -> str | None:
        return self.database.write_refusal

    def transaction(self) -> AbstractContextManager[Any]:
        return self.database.transaction()

    def image_path_for(self, sha: str, ext: str) -> Path:
        return self.database.image_path_for(sha, ext)

    def get_meta(self, key: str) -> str | None:
        return self.database.get_meta(key)

    def set_meta(self, key: str, value: str) -> None:
        self.database.set_meta(key, value)

    def refuse_writes(self, why: str) -> None:
        self.database.refuse_writes(why)

    # -- the parts' methods ---------------------------------------------------------------------------
    version = property(lambda self: self.changes.version, doc="The index version (``ChangeLog.version``).")
    changes_since = _forward("changes", ChangeLog.changes_since)
    indexed_ids = _forward("changes", ChangeLog.indexed_ids)
    pending = _forward("queue", Queue.pending)
    claim = _forward("queue", Queue.claim)
    release = _forward("queue", Queue.release)
    attempts = _forward("queue", Queue.attempts)
    start_attempts = _forward("queue", Queue.start_attempts)
    end_attempts = _forward("queue", Queue.end_attempts)
    quarantined = _forward("queue", Queue.quarantined)
    complete = _forward("queue", Queue.complete)
    job = _forward("queue", Queue.job)
    head = _forward("generations", Generations.head)
    generation_state = _forward("generations", Generations.generation_state)
    record_first_pipeline = _forward("generations", Generations.record_first_pipeline)
    code_stream = _forward("generations", Generations.code_stream)
    all_codes = _forward("generations", Generations.all_codes)
    reindex_target = _forward("generations", Generations.reindex_target)
    start_reindex = _forward("generations", Generations.start_reindex)
    abandon_reindex = _forward("generations", Generations.abandon_reindex)
    reindex_todo = _forward("generations", Generations.reindex_todo)
    put_next_codes = _forward("generations", Generations.put_next_codes)
    reindex_missing = _forward("generations", Generations.reindex_missing)
    switch_generation = _forward("generations", Generations.switch_generation)
    migrate_switched = _forward("generations", Generations.migrate_switched)
    database_id = property(lambda self: self.identity.database_id, doc="The database's id (``Identity``).")
    checkpoint = _forward("identity", Identity.checkpoint)
    ref_high_water = _forward("identity", Identity.ref_high_water)
    binding = _forward("identity", Identity.binding)
    binding_state = _forward("identity", Identity.binding_state)
    retire_snapshot = _forward("identity", Identity.retire_snapshot)
    queued_removals = _forward("removals", Removals.queued_removals)
    remove_queued = _forward("removals", Removals.remove_queued)
    remove_unnamed = _forward("removals", Removals.remove_unnamed)
    named_files = _forward("removals", Removals.named_files)
    holds_tables = _forward("maintenance", Maintenance.holds_tables)
    stored_rows = _forward("maintenance", Maintenance.stored_rows)

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

    # -- adding ---------------------------------------------------------------------------------------
    def existing_ids(self, shas: Sequence[str]) -> dict[str, int]:
        return dict(self._ids_of(self.db, shas))

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
                    syncfs(self.images_dir)
                fsync_dir(self.images_dir)

    def insert_rows(
        self, items: Sequence[NewReference], job: bool = False
    ) -> tuple[list[tuple[int, bool]], str | None]:
        """Insert rows in one transaction; identical bytes (already stored, or racing in from another process
        at this very moment) come back as the existing id with ``created`` False. Encoded items are stored
        indexed and logged as index changes in the same transaction. Each created row's file is checked (and
        written again if a delete removed it meanwhile) before the commit: see ``app.storage.removals``."""
        job_id = uuid.uuid4().hex if job else None
        now = _now()
        with self.transaction() as db:
            made = self.backend.insert_refs(db, _INSERT_COLS, [_row(it, now) for it in items])
            self.changes.log_adds(db, [i for i, status in made.values() if status == "indexed"])
            others = sorted({it.sha256 for it in items} - set(made))
            known = dict(self._ids_of(db, others)) if others else {}
            out: list[tuple[int, bool]] = []
            created: list[NewReference] = []
            for it in items:
                if it.sha256 in made:
                    out.append((made.pop(it.sha256)[0], True))
                    known[it.sha256] = out[-1][0]
                    created.append(it)
                else:
                    out.append((int(known[it.sha256]), False))
            self._files_for(db, created)
            if job_id is not None:
                self.queue.record_job(db, job_id, now, out)
        with self.database.lock:
            self.backend.after_bulk_insert(self.db, len(created), max((i for i, _ in out), default=0))
        return out, job_id

    def _ids_of(self, db, shas: Sequence[str]) -> list[tuple[str, int]]:
        return db.execute(
            "SELECT sha256, id FROM refs WHERE sha256 IN (SELECT value FROM json_each(?))", (json.dumps(list(shas)),)
        ).fetchall()

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
        self.removals.unqueue(db, names)

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
            db.execute("DELETE FROM encode_attempts WHERE ref_id=?", (ref_id,))
            if row[2] == "indexed":
                self.changes.log(db, ref_id, "delete")
            name = self.image_path_for(row[0], row[1]).name
            self.removals.queue(db, name)
        try:
            _, failed = self.remove_queued([name])
        except StorageUnavailable as e:
            log.warning("reference %d deleted; removing its image is queued (%s)", ref_id, e)
            return "queued"
        return "queued" if failed else "removed"

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
                self.changes.log(db, ref_id, "move")
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
            f"SELECT {_COLS} FROM refs WHERE id IN (SELECT value FROM json_each(?))", (ids_json(ids),)
        ).fetchall()
        return {r[0]: Reference(*r) for r in rows}

    def image_path(self, ref_id: int) -> Path | None:
        """Where the reference's image is (or should be); None when there is no such reference."""
        row = self.db.execute("SELECT sha256, image_ext FROM refs WHERE id=?", (ref_id,)).fetchone()
        return self.image_path_for(row[0], row[1]) if row else None

    def list(
        self, offset: int = 0, limit: int = 50, bbox: tuple[float, float, float, float] | None = None
    ) -> tuple[list[Reference], int]:
        """A page by position, with the count of every matching row: both cost O(rows) (the count reads
        them all, OFFSET skips them one by one), so collections of 10^5 or more page with ``page``."""
        where, args = _bbox_where(bbox)
        total = self.db.execute(f"SELECT COUNT(*) FROM refs {where}", args).fetchone()[0]
        rows = self.db.execute(
            f"SELECT {_COLS} FROM refs {where} ORDER BY id LIMIT ? OFFSET ?", [*args, limit, offset]
        ).fetchall()
        return [Reference(*r) for r in rows], total

    def page(
        self,
        after: int | None = None,
        before: int | None = None,
        limit: int = 50,
        bbox: tuple[float, float, float, float] | None = None,
    ) -> KeysetPage:
        """A page by id (keyset): the rows just after ``after`` or just before ``before``, in id order. It
        reads ``limit`` + 1 rows by the primary key plus one probe for a row on the other side, so a page
        deep in 10^6 references costs what the first does (an OFFSET walks every row it skips). With a
        bbox that holds few rows the reads walk the id order past the rows outside it, up to all of them."""
        where, args = _bbox_where(bbox)
        join = "AND" if where else "WHERE"
        if before is not None:
            rows = self.db.execute(
                f"SELECT {_COLS} FROM refs {where} {join} id < ? ORDER BY id DESC LIMIT ?", [*args, before, limit + 1]
            ).fetchall()
            more_before = len(rows) > limit
            rows = rows[:limit][::-1]
            # An empty page (its last rows deleted) still points at the rows after it, so a client is not
            # left on a page with no way out.
            first, last = (rows[0][0], rows[-1][0]) if rows else (before, max(before - 1, 0))  # ids start at 1
            more_after = self._any_beyond(where, join, args, ">", last)
        else:
            start = -1 if after is None else after
            rows = self.db.execute(
                f"SELECT {_COLS} FROM refs {where} {join} id > ? ORDER BY id LIMIT ?", [*args, start, limit + 1]
            ).fetchall()
            more_after = len(rows) > limit
            rows = rows[:limit]
            first, last = (rows[0][0], rows[-1][0]) if rows else (min(start + 1, _MAX_ID), start)
            more_before = self._any_beyond(where, join, args, "<", first)
        return KeysetPage(
            [Reference(*r) for r in rows],
            next_after=last if more_after else None,
            prev_before=first if more_before else None,
        )

    def _any_beyond(self, where: str, join: str, args: list, op: str, ref_id: int) -> bool:
        q = f"SELECT 1 FROM refs {where} {join} id {op} ? LIMIT 1"
        return self.db.execute(q, [*args, ref_id]).fetchone() is not None

    def count_in(self, bbox: tuple[float, float, float, float] | None = None) -> int:
        """Rows (any status) inside a bbox or in all: O(rows), for a person's 'of N', not for every page."""
        where, args = _bbox_where(bbox)
        return self.db.execute(f"SELECT COUNT(*) FROM refs {where}", args).fetchone()[0]

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

    def extent(self) -> tuple[float, float, float, float] | None:
        """(min_lon, min_lat, max_lon, max_lat) of every stored reference, None when there is none. Four
        reads of one end of an index each (refs_lat_lon, refs_lon): constant cost at 10^6 references, so
        /locate can show what the collection covers with every answer."""
        q = "SELECT {f}({c}) FROM refs"
        lo_lat = self.db.execute(q.format(f="min", c="lat")).fetchone()[0]
        if lo_lat is None:
            return None
        hi_lat = self.db.execute(q.format(f="max", c="lat")).fetchone()[0]
        lo_lon = self.db.execute(q.format(f="min", c="lon")).fetchone()[0]
        hi_lon = self.db.execute(q.format(f="max", c="lon")).fetchone()[0]
        return float(lo_lon), float(lo_lat), float(hi_lon), float(hi_lat)

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
                "SELECT id, lat, lon FROM refs WHERE id IN (SELECT value FROM json_each(?))", (ids_json(ids),)
            )
        }
        pos = np.array([found.get(i, (np.nan, np.nan)) for i in ids], np.float64)
        return pos[:, 0], pos[:, 1]
