"""The ingestion queue: pending rows are the durable queue. A bulk run claims the rows it encodes itself;
an upload's job records which references it created, so its progress can be read back."""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.storage.changes import ChangeLog
from app.storage.database import Database, Part, blob, ids_json

#: How a quarantined row's error starts (``Queue.start_attempts``): ``geoloc check`` and the jobs API list them.
QUARANTINED = "quarantined"


@dataclass(frozen=True)
class JobItem:
    reference_id: int
    duplicate: bool
    status: str  # pending, indexed, failed, or deleted (no row any more)
    error: str | None

    @property
    def quarantined(self) -> bool:
        return self.status == "failed" and (self.error or "").startswith(f"{QUARANTINED}:")


@dataclass(frozen=True)
class Job:
    """An upload's progress: its items in upload order and how many are in each state."""

    id: str
    created_at: str
    status: str  # queued, running, done or failed
    total: int
    pending: int
    indexed: int
    failed: int
    deleted: int
    items: list[JobItem]

    @property
    def quarantined(self) -> int:
        return sum(1 for it in self.items if it.quarantined)


def _job_status(items: Sequence[JobItem], counts: dict[str, int]) -> str:
    if counts["pending"] == len(items):
        return "queued"
    if counts["pending"]:
        return "running"
    return "failed" if counts["failed"] == len(items) else "done"


class Queue(Part):
    """The ingestion queue's tables: ``jobs`` and ``job_items`` (an upload's references, in order),
    ``claims`` (pending rows a bulk run (``geoloc ingest``) encodes itself: a worker skips them until the
    lease ends, so the rows of a run that crashed go back to the queue by themselves) and
    ``encode_attempts`` (counted and committed before each attempt: a row whose encoding takes the process
    down can never report its own failure, and was retried forever on every host in turn)."""

    def __init__(self, database: Database, changes: ChangeLog):
        super().__init__(database)
        self.changes = changes

    def pending(self, limit: int, after: int = 0) -> list[tuple[int, Path]]:
        """The next pending rows in id order, except those another run claimed and whose lease still runs."""
        rows = self.database.db.execute(
            "SELECT r.id, r.sha256, r.image_ext FROM refs r LEFT JOIN claims c ON c.ref_id = r.id "
            "WHERE r.status='pending' AND r.id > ? AND (c.expires IS NULL OR c.expires <= ?) ORDER BY r.id LIMIT ?",
            (after, time.time(), limit),
        ).fetchall()
        return [(r[0], self.database.image_path_for(r[1], r[2])) for r in rows]

    def claim(self, ids: Sequence[int], owner: str, lease_s: float) -> None:
        """Claim rows for ``owner`` for ``lease_s`` seconds (one statement for the whole list); a claim held
        by another owner is taken over only once its lease has ended."""
        with self.database.transaction() as db:
            db.execute(
                "INSERT INTO claims(ref_id, owner, expires) SELECT value, ?, ? FROM json_each(?) WHERE true "
                "ON CONFLICT(ref_id) DO UPDATE SET owner=excluded.owner, expires=excluded.expires "
                "WHERE claims.owner = excluded.owner OR claims.expires <= ?",
                (owner, time.time() + lease_s, ids_json(ids), time.time()),
            )

    def release(self, owner: str, ids: Sequence[int] | None = None) -> None:
        """Drop ``owner``'s claims on ``ids`` (all of them when None): done rows, or the end of a run."""
        with self.database.transaction() as db:
            if ids is None:
                db.execute("DELETE FROM claims WHERE owner=?", (owner,))
            else:
                db.execute(
                    "DELETE FROM claims WHERE owner=? AND ref_id IN (SELECT value FROM json_each(?))",
                    (owner, ids_json(ids)),
                )

    def attempts(self, ids: Sequence[int]) -> dict[int, int]:
        """How many encodings of ``ids`` were started and never completed (rows with none are left out)."""
        rows = self.database.db.execute(
            "SELECT ref_id, attempts FROM encode_attempts WHERE ref_id IN (SELECT value FROM json_each(?))",
            (ids_json(ids),),
        ).fetchall()
        return {int(i): int(n) for i, n in rows}

    def start_attempts(self, ids: Sequence[int], limit: int) -> list[int]:
        """Count one more attempt of each of ``ids``, committed before the encoding starts. A row already
        attempted ``limit`` times is quarantined instead (failed, its error saying so: never tried again) and
        returned."""
        with self.database.transaction() as db:
            spent = [
                int(r[0])
                for r in db.execute(
                    "SELECT ref_id FROM encode_attempts WHERE ref_id IN (SELECT value FROM json_each(?)) "
                    "AND attempts >= ?",
                    (ids_json(ids), limit),
                ).fetchall()
            ]
            if spent:
                db.execute(
                    "UPDATE refs SET status='failed', error=? WHERE status='pending' "
                    "AND id IN (SELECT value FROM json_each(?))",
                    (
                        f"{QUARANTINED}: its encoding was started {limit} times and never finished (the process "
                        "encoding it stopped each time); delete it, or fix the image and upload it again",
                        ids_json(spent),
                    ),
                )
                db.execute(
                    "DELETE FROM encode_attempts WHERE ref_id IN (SELECT value FROM json_each(?))", (ids_json(spent),)
                )
            db.execute(
                "INSERT INTO encode_attempts(ref_id, attempts) SELECT value, 1 FROM json_each(?) WHERE true "
                "ON CONFLICT(ref_id) DO UPDATE SET attempts = encode_attempts.attempts + 1",
                (ids_json([i for i in ids if i not in set(spent)]),),
            )
        return spent

    def end_attempts(self, ids: Sequence[int]) -> None:
        """The encoding of ``ids`` returned (whatever its outcome: codes, a failure, a storage retry): none of
        them took the process down. Only a process that died leaves its count behind."""
        with self.database.transaction() as db:
            db.execute("DELETE FROM encode_attempts WHERE ref_id IN (SELECT value FROM json_each(?))", (ids_json(ids),))

    def quarantined(self, limit: int = 100) -> list[tuple[int, str]]:
        """Quarantined rows (id, error), oldest first, at most ``limit``."""
        rows = self.database.db.execute(
            "SELECT id, error FROM refs WHERE status='failed' AND error LIKE ? ORDER BY id LIMIT ?",
            (f"{QUARANTINED}:%", limit),
        ).fetchall()
        return [(int(i), str(e)) for i, e in rows]

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
        with self.database.transaction() as db:
            if fingerprint is not None and not self.database.fingerprint_is(db, fingerprint):
                return []
            for ref_id, fcode, bcode, error in results:
                if error is not None:
                    db.execute(
                        "UPDATE refs SET status='failed', error=? WHERE id=? AND status='pending'", (error, ref_id)
                    )
                    continue
                cur = db.execute(
                    "UPDATE refs SET float_code=?, binary_code=?, status='indexed' WHERE id=? AND status='pending'",
                    (blob(fcode, np.float32), blob(bcode, np.uint8), ref_id),
                )
                if cur.rowcount:
                    self.changes.log(db, ref_id, "add")
                    done.append(ref_id)
        return done

    def record_job(
        self, db: sqlite3.Connection, job_id: str, created_at: str, items: Sequence[tuple[int, bool]]
    ) -> None:
        """Inside an add's write transaction: the job of ``items`` ((reference id, created), in order)."""
        db.execute("INSERT INTO jobs(id, created_at) VALUES(?, ?)", (job_id, created_at))
        rows = [(job_id, n, ref_id, int(not created)) for n, (ref_id, created) in enumerate(items)]
        self.database.backend.copy_rows(db, "job_items", ("job_id", "position", "ref_id", "duplicate"), rows)

    def job(self, job_id: str) -> Job | None:
        row = self.database.db.execute("SELECT created_at FROM jobs WHERE id=?", (job_id,)).fetchone()
        if row is None:
            return None
        rows = self.database.db.execute(
            "SELECT j.position, j.ref_id, j.duplicate, r.status, r.error FROM job_items j "
            "LEFT JOIN refs r ON r.id = j.ref_id WHERE j.job_id=? ORDER BY j.position",
            (job_id,),
        ).fetchall()
        items = [JobItem(i[1], bool(i[2]), i[3] or "deleted", i[4]) for i in rows]
        counts = {s: sum(1 for it in items if it.status == s) for s in ("pending", "indexed", "failed", "deleted")}
        return Job(job_id, row[0], _job_status(items, counts), len(items), items=items, **counts)
