"""The index's change log: every change *of the index* (a reference encoded and added, an indexed reference
deleted or moved) appends one row ``(version, ref_id, op)`` in the same transaction as the change itself. The
index version is the log's last version; a process holding the index at version ``v`` catches up by reading
exactly the changes after ``v`` (with their codes, in one query)."""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass

import numpy as np

from app.storage.database import Part, ids_json
from app.storage.generations import CODES


@dataclass(frozen=True)
class Change:
    version: int
    ref_id: int
    op: str  # add | delete | move
    float_code: bytes | None
    binary_code: bytes | None
    lat: float | None = None  # the reference's position now (an index that holds positions writes it)
    lon: float | None = None


class ChangeLog(Part):
    """The ``changes`` table."""

    def log(self, db: sqlite3.Connection, ref_id: int, op: str) -> None:
        """Inside a write transaction: append one change of the index."""
        db.execute("INSERT INTO changes(ref_id, op) VALUES(?, ?)", (ref_id, op))
        self.database.backend.notify(db)

    def log_adds(self, db: sqlite3.Connection, ids: list[int]) -> None:
        """Inside a write transaction: append an add of each of ``ids``, in id order (a bulk insert)."""
        if ids:
            db.execute(
                "INSERT INTO changes(ref_id, op) SELECT value, 'add' FROM json_each(?) ORDER BY value",
                (ids_json(sorted(ids)),),
            )
            self.database.backend.notify(db)

    @property
    def version(self) -> int:
        """The index version: the change log's last entry. Pending uploads do not move it. Read under the
        store's lock: on the connection this process shares between threads, a read inside another thread's
        open write transaction would see changes that may yet roll back."""
        with self.database.lock:
            return int(self.database.db.execute("SELECT COALESCE(MAX(version), 0) FROM changes").fetchone()[0])

    def changes_since(self, version: int) -> list[Change]:
        """The index changes after ``version``, oldest first, each add and move with the reference's codes and
        position now (NULL when the row was deleted since: a later delete entry follows). Under the lock, like
        ``version``."""
        with self.database.lock:
            rows = self.database.db.execute(
                f"SELECT c.version, c.ref_id, c.op, {CODES}, r.lat, r.lon FROM changes c "
                "LEFT JOIN refs r ON r.id = c.ref_id AND r.status = 'indexed' AND c.op IN ('add', 'move') "
                "LEFT JOIN switched_codes s ON s.ref_id = r.id "
                "WHERE c.version > ? ORDER BY c.version",
                (version,),
            ).fetchall()
        return [Change(*r) for r in rows]

    def indexed_ids(self) -> np.ndarray:
        rows = self.database.db.execute("SELECT id FROM refs WHERE status='indexed' ORDER BY id").fetchall()
        return np.array([r[0] for r in rows], np.int64)
