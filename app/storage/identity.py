"""Durability and identity: the database's random id, checkpoints into the main file, and what binds a
snapshot of the index to this database at one state (see ``app.storage.snapshots``)."""

from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass

from app.storage.database import Part

log = logging.getLogger("geoloc.store")


@dataclass(frozen=True)
class Binding:
    """What binds a snapshot of the index at one version to a database: its id (None only for a database
    made by an older version and opened read-only since), the reference id high-water mark, and the change
    log's entry at that version ``[ref_id, op, sha256]`` (the sha256 is None once the reference is deleted)."""

    database_id: str | None
    ref_high_water: int | None
    last_change: list | None


class Identity(Part):
    """The database's id (meta ``database_id``), its checkpoints and id counters."""

    def ensure_id(self) -> None:
        """Give the database its identity (a random id in meta) the first time it is opened, by this version
        or an older one that made none, and checkpoint it at once: the main file alone then names the
        database, so a copy of it without its ``-wal`` is recognised as this database at an older state."""
        if self.database.get_meta("database_id") is not None:
            return
        with self.database.transaction() as db:
            db.execute(
                "INSERT INTO meta(key, value) VALUES('database_id', ?) ON CONFLICT(key) DO NOTHING", (uuid.uuid4().hex,)
            )
        if self.database.db.execute("SELECT COUNT(*) FROM refs").fetchone()[0]:
            log.info("%s had no database id (made by an older version): it has one now", self.database.data_dir)
        self.checkpoint("PASSIVE")

    @property
    def database_id(self) -> str | None:
        """None only for a database made by an older version and opened read-only since."""
        return self.database.get_meta("database_id")

    def checkpoint(self, mode: str = "PASSIVE", timeout_s: float = 2.0) -> tuple[int, int, int] | None:
        """Copy the log's committed pages into the main database file (SQLite's WAL: a copy of the main file
        alone then holds every row): (busy, WAL frames, frames checkpointed), or None when it could not run
        or the backend has no such step (PostgreSQL's WAL is the server's). PASSIVE never waits; TRUNCATE,
        at a clean stop, waits up to ``timeout_s`` for readers."""
        if self.database.read_only:
            return None
        return self.database.backend.checkpoint(mode, timeout_s, self.database.files, self.database.refuse_writes)

    def ref_high_water(self) -> int:
        """The largest reference id ever handed out (the id counter, or a larger row id)."""
        return self.database.backend.ref_high_water(self.database.db)

    def binding(self, version: int) -> Binding:
        """What binds a snapshot of the index at ``version`` to this database: its id, the reference id
        high-water mark, and the change log's entry at ``version`` with its image's sha256 (two databases
        that diverged after a common past disagree there)."""
        with self.database.read_snapshot():
            return Binding(self.database_id, self.ref_high_water(), self._change_at(version))

    def _change_at(self, version: int) -> list | None:
        """The change log's entry at ``version``: [ref_id, op, the reference's sha256 (None once deleted)]."""
        row = self.database.db.execute(
            "SELECT c.ref_id, c.op, r.sha256 FROM changes c LEFT JOIN refs r ON r.id = c.ref_id WHERE c.version=?",
            (version,),
        ).fetchone()
        return list(row) if row else None

    def binding_state(self, version: int) -> tuple[str | None, int, list | None]:
        """(database id, index version, change-log entry at ``version``) read together, to check a snapshot."""
        with self.database.read_snapshot() as db:
            head = int(db.execute("SELECT COALESCE(MAX(version), 0) FROM changes").fetchone()[0])
            return self.database_id, head, self._change_at(version)

    def retire_snapshot(self, version: int, ref_high_water: int | None) -> None:
        """A snapshot (of change-log ``version``, knowing ids up to ``ref_high_water``) was refused: raise
        AUTOINCREMENT's counters past what it knew, so the ids of references it indexes (lost from this
        database) are never handed out again, and the change log never again reaches its version with other
        entries (the refused snapshot can never match later)."""
        if self.database.read_only:
            return
        marks = {("refs", "id"): int(ref_high_water or 0), ("changes", "version"): int(version or 0)}
        with self.database.transaction() as db:
            for (table, column), mark in marks.items():
                self.database.backend.raise_counter(db, table, column, mark)
