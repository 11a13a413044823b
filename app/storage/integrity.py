"""Whether the SQLite files this process writes through are still the ones in the data dir.

Why: a ``-wal`` deleted (or the database replaced) under a live server left it acknowledging writes into a
file no other process could see; every checkpoint failed with "disk I/O error" in the log only, /ready said
200, and after a kill -9 the uploads accepted since were gone and their ids handed out again.
The store now records which files it opened, checks them (two ``stat`` calls) before each write
transaction, and once they differ, or a checkpoint fails with an I/O error, it refuses every write for the
rest of the process's life (``StorageUnavailable``, a 503) and /ready says why.

What this process still sees is not lost: its own connection keeps the removed ``-wal`` open, so a copy of
the database as it sees it (``sqlite3.Connection.backup``) is written beside it for the operator to put back.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

from app.permissions import create_private_file

log = logging.getLogger("geoloc.store")


@dataclass(frozen=True)
class FileId:
    device: int
    inode: int

    @classmethod
    def of(cls, path: Path) -> FileId | None:
        try:
            st = os.stat(path)
        except FileNotFoundError:
            return None
        return cls(st.st_dev, st.st_ino)


class DatabaseFiles:
    """The database file and its ``-wal`` as this process opened them, and the reason writes are refused
    (None while they are not)."""

    def __init__(self, db_path: Path):
        self.db_path = Path(db_path)
        self.wal_path = Path(f"{db_path}-wal")
        self.opened = (FileId.of(self.db_path), FileId.of(self.wal_path))
        self.refusal: str | None = None

    def changed(self) -> str | None:
        """What differs from what was opened, in words; None while both files are the ones opened."""
        for path, opened in zip((self.db_path, self.wal_path), self.opened, strict=True):
            now = FileId.of(path)
            if opened is not None and now != opened:
                what = "was removed" if now is None else "was replaced by another file"
                return f"{path.name} {what} while this process had it open"
        return None

    def refuse(self, why: str, connection: sqlite3.Connection | None) -> str:
        """Refuse writes from now on; rescue what ``connection`` sees into a copy beside the database."""
        if self.refusal is not None:
            return self.refusal
        rescued = self._rescue(connection) if connection is not None else None
        advice = (
            f"; everything this process had committed is in {rescued.name}: stop every process of this data dir, "
            f"replace {self.db_path.name} with it (and remove {self.wal_path.name} and "
            f"{self.db_path.name}-shm), then start again"
            if rescued is not None
            else "; stop every process of this data dir and run `geoloc check`"
        )
        self.refusal = f"writes are refused: {why}{advice}"
        log.error("%s", self.refusal)
        return self.refusal

    def _rescue(self, connection: sqlite3.Connection) -> Path | None:
        target = self.db_path.with_name(f"references.rescued-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.sqlite")
        try:
            create_private_file(target)
            copy = sqlite3.connect(target)
            try:
                connection.backup(copy)
            finally:
                copy.close()
        except (OSError, sqlite3.Error) as e:
            log.error("could not copy the database as this process sees it into %s: %s", target, e)
            return None
        return target
