"""Image files to remove, queued in the transaction that deletes the row naming them.

A file is unlinked only under the write lock and only while no row names it (``_unlink_unnamed``), and an
add commits a row only after checking, under the same lock, that its file is there (``insert_rows``): so
whichever of an upload and a delete of the same bytes commits last, across processes, a committed row
always names a file. A removal that fails (a read-only folder) stays queued and is retried by the writer
process and by ``geoloc check --repair``.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import time
from collections.abc import Sequence

from app.storage.database import Part
from app.storage.feature_files import delete_everywhere
from app.storage.files import THUMBNAILS

log = logging.getLogger("geoloc.store")


class Removals(Part):
    """The ``removals`` table and the unlinks it drives."""

    def queue(self, db: sqlite3.Connection, name: str) -> None:
        """Inside the write transaction that deletes the row naming ``name``."""
        db.execute(
            "INSERT INTO removals(name, queued_at) VALUES(?, ?) ON CONFLICT(name) DO NOTHING", (name, time.time())
        )

    def unqueue(self, db: sqlite3.Connection, names: Sequence[str]) -> None:
        """Inside an add's write transaction: the names are in use again."""
        db.execute("DELETE FROM removals WHERE name IN (SELECT value FROM json_each(?))", (json.dumps(list(names)),))

    def queued_removals(self) -> list[str]:
        """The file names still queued for removal (an empty list on a data dir from before the queue)."""
        try:
            with self.database.lock:  # not inside another thread's open transaction on this shared connection
                return [
                    r[0] for r in self.database.db.execute("SELECT name FROM removals ORDER BY queued_at").fetchall()
                ]
        except sqlite3.OperationalError:  # a read-only open of a data dir without the table
            return []

    def remove_queued(self, names: Sequence[str] | None = None, limit: int = 1000) -> tuple[list[str], list[str]]:
        """Remove queued files (those in ``names``, or up to ``limit`` of the oldest): each is unlinked under
        the write lock unless a row names it again (an upload of the same bytes since), and leaves the queue
        unless its unlink failed. Returns (removed, failed)."""
        with self.database.transaction() as db:
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
        with self.database.transaction() as db:
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
                (self.database.images_dir / name).unlink(missing_ok=True)
                self._unlink_thumbnails(name)
                delete_everywhere(self.database.data_dir, name.split(".", 1)[0])
                removed.append(name)
            except OSError as e:
                log.warning("cannot remove %s now: %s", self.database.images_dir / name, e)
                failed.append(name)
        return removed, failed

    def _unlink_thumbnails(self, name: str) -> None:
        """The image's thumbnails, one per size ever served (a handful of folders: no scan of the files)."""
        folder = self.database.images_dir / THUMBNAILS
        if folder.is_dir():
            sha = name.split(".", 1)[0]
            for size in folder.iterdir():
                (size / f"{sha}.jpg").unlink(missing_ok=True)

    def named_files(self, names: Sequence[str], db: sqlite3.Connection | None = None) -> set[str]:
        """Those of ``names`` (image file names) that a row names: one lookup of the sha256 index each."""
        if not names:
            return set()
        shas = json.dumps([n.split(".", 1)[0] for n in names])
        conn = db or self.database.db
        with self.database.lock:
            rows = conn.execute(
                "SELECT sha256, image_ext FROM refs WHERE sha256 IN (SELECT value FROM json_each(?))", (shas,)
            ).fetchall()
        return {f"{sha}.{ext}" for sha, ext in rows} & set(names)
