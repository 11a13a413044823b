"""Durability and identity: the database's random id, checkpoints into the main file, and what binds a
snapshot of the index to this database at one state (see ``app.storage.snapshots``)."""

from __future__ import annotations

import logging
import sqlite3
import uuid
from dataclasses import dataclass

from app.storage.database import DB_NAME, Database

log = logging.getLogger("geoloc.store")


@dataclass(frozen=True)
class Binding:
    """What binds a snapshot of the index at one version to a database: its id (None only for a database
    made by an older version and opened read-only since), the reference id high-water mark, and the change
    log's entry at that version ``[ref_id, op, sha256]`` (the sha256 is None once the reference is deleted)."""

    database_id: str | None
    ref_high_water: int | None
    last_change: list | None


class Identity(Database):
    def _ensure_database_id(self) -> None:
        """Give the database its identity (a random id in meta) the first time it is opened, by this version
        or an older one that made none, and checkpoint it at once: the main file alone then names the
        database, so a copy of it without its ``-wal`` is recognised as this database at an older state."""
        if self.get_meta("database_id") is not None:
            return
        with self.transaction() as db:
            db.execute(
                "INSERT INTO meta(key, value) VALUES('database_id', ?) ON CONFLICT(key) DO NOTHING", (uuid.uuid4().hex,)
            )
        if self.db.execute("SELECT COUNT(*) FROM refs").fetchone()[0]:
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
        transactions nor holds the store's lock. PostgreSQL has no such step (its WAL is the server's)."""
        if self.read_only or self.engine == "postgres":
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
            # Not a reader in the way but the files themselves: a removed -wal gives "disk I/O error". (A full
            # disk is "database or disk is full": it passes, and writes work again once there is room.)
            why = self.files.changed() if self.files is not None else None
            if why is None and "i/o error" in str(e).lower():
                why = f"a checkpoint of the database failed ({e})"
            if why is not None:
                self.refuse_writes(why)
            return None
        if row[0]:
            log.info(
                "checkpoint %s of %s: a reader holds %d of %d WAL frames", mode, self.data_dir, row[1] - row[2], row[1]
            )
        return int(row[0]), int(row[1]), int(row[2])

    def ref_high_water(self) -> int:
        """The largest reference id ever handed out (AUTOINCREMENT's counter, or a larger row id)."""
        if self.engine == "postgres":
            row = self.db.execute(
                "SELECT GREATEST(COALESCE(pg_sequence_last_value(pg_get_serial_sequence('refs', 'id')), 0), "
                "COALESCE((SELECT MAX(id) FROM refs), 0))"
            ).fetchone()
            return int(row[0])
        row = self.db.execute(
            "SELECT MAX(COALESCE((SELECT seq FROM sqlite_sequence WHERE name='refs'), 0), "
            "COALESCE((SELECT MAX(id) FROM refs), 0))"
        ).fetchone()
        return int(row[0])

    def binding(self, version: int) -> Binding:
        """What binds a snapshot of the index at ``version`` to this database: its id, the reference id
        high-water mark, and the change log's entry at ``version`` with its image's sha256 (two databases
        that diverged after a common past disagree there)."""
        with self.read_snapshot():
            return Binding(self.database_id, self.ref_high_water(), self._change_at(version))

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

    def retire_snapshot(self, version: int, ref_high_water: int | None) -> None:
        """A snapshot (of change-log ``version``, knowing ids up to ``ref_high_water``) was refused: raise
        AUTOINCREMENT's counters past what it knew, so the ids of references it indexes (lost from this
        database) are never handed out again, and the change log never again reaches its version with other
        entries (the refused snapshot can never match later)."""
        if self.read_only:
            return
        marks = {"refs": int(ref_high_water or 0), "changes": int(version or 0)}
        with self.transaction() as db:
            for table, mark in marks.items():
                if self.engine == "postgres":  # sequences: an identity column's counter only ever rises
                    if mark:
                        column = "id" if table == "refs" else "version"
                        db.execute(
                            "SELECT setval(s, GREATEST(?, COALESCE(pg_sequence_last_value(s), 0))) "
                            "FROM pg_get_serial_sequence(?, ?) AS s",
                            (mark, table, column),
                        )
                    continue
                cur = db.execute("UPDATE sqlite_sequence SET seq = MAX(seq, ?) WHERE name = ?", (mark, table))
                if not cur.rowcount and mark:
                    db.execute("INSERT INTO sqlite_sequence(name, seq) VALUES(?, ?)", (table, mark))
