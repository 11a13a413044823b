"""The ingestion journal: which source files a previous `geoloc ingest` already stored, so a re-run skips
them without reading them again.

Why a journal beside the content hashes: the store already refuses a second copy of the same bytes, but
finding that out means reading and hashing every file, which on 10^6 photos is most of a run. The journal
keys a file by (path, size, mtime_ns), which a ``stat`` gives, so a resumed run costs one stat per file and
one indexed read per chunk. A file that changed (another size or mtime) misses the journal and is read
again; if its bytes are the same, the content hash still finds the stored reference.

Only stored files are recorded: a skipped file (no GPS, damaged, too large) is read again by the next run,
since the limits or the installed decoders (pillow-heif) may have changed. It is its own SQLite file in the
data dir (``ingest-journal.sqlite``), written once per chunk, never per file.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from app.storage.errors import storage_guard

JOURNAL_NAME = "ingest-journal.sqlite"
SCHEMA = """
CREATE TABLE IF NOT EXISTS files (
    path TEXT PRIMARY KEY,
    size INTEGER NOT NULL,
    mtime_ns INTEGER NOT NULL,
    ref_id INTEGER NOT NULL
);
"""


@dataclass(frozen=True)
class FileKey:
    """A source file as ``stat`` sees it: a different size or mtime means a different file."""

    path: str  # absolute
    size: int
    mtime_ns: int


class Journal:
    """(path, size, mtime_ns) -> reference id, for the files earlier runs stored in this data dir."""

    def __init__(self, data_dir: Path):
        self.path = Path(data_dir) / JOURNAL_NAME
        with storage_guard("opening the ingestion journal"):
            self.db = sqlite3.connect(self.path, isolation_level=None)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA busy_timeout=10000")
            self.db.executescript(SCHEMA)

    def close(self) -> None:
        self.db.close()

    def lookup(self, keys: Sequence[FileKey]) -> dict[str, int]:
        """The reference ids of the ``keys`` recorded with the same size and mtime, by path (one read)."""
        if not keys:
            return {}
        wanted = {k.path: k for k in keys}
        rows = self.db.execute(
            "SELECT path, size, mtime_ns, ref_id FROM files WHERE path IN (SELECT value FROM json_each(?))",
            (json.dumps(list(wanted)),),
        ).fetchall()
        return {p: ref for p, size, mtime, ref in rows if (wanted[p].size, wanted[p].mtime_ns) == (size, mtime)}

    def record(self, entries: Sequence[tuple[FileKey, int]]) -> None:
        """Record stored files (and the reference each became) in one transaction."""
        if not entries:
            return
        with storage_guard("writing the ingestion journal"):
            self.db.execute("BEGIN IMMEDIATE")
            try:
                self.db.executemany(
                    "INSERT INTO files(path, size, mtime_ns, ref_id) VALUES(?,?,?,?) ON CONFLICT(path) DO UPDATE "
                    "SET size=excluded.size, mtime_ns=excluded.mtime_ns, ref_id=excluded.ref_id",
                    [(k.path, k.size, k.mtime_ns, ref) for k, ref in entries],
                )
                self.db.execute("COMMIT")
            except BaseException:
                if self.db.in_transaction:
                    self.db.execute("ROLLBACK")
                raise

    def __len__(self) -> int:
        return self.db.execute("SELECT COUNT(*) FROM files").fetchone()[0]
