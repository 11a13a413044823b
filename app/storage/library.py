"""The library's journal: ``DATA_DIR/library.sqlite`` holds every scanned photo's suggestion, the user's
decision on it and what was written back, so that

- a second scan skips what is done (a photo is keyed by path, size and mtime, as the ingest journal does);
- a review survives a restart of the server and can be made from the CLI, the API or the page alike;
- every write can be undone (its backup is recorded before exiftool touches anything).

One small SQLite file beside the collection's; one connection guarded by a lock (the API's thread pool and
a scan's thread both use it), WAL so that a reader never waits for a scan. It lives in the data dir of the
host that scanned, also where the collection is on PostgreSQL: a library's journal is per host.

A scan's id is random (``secrets.token_hex``), made once per folder and found again by its folder: an id
derived from the path would let anyone who can guess a folder name address its scan."""

from __future__ import annotations

import json
import secrets
import shutil
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass
from pathlib import Path

#: The journal's file and the folders of write-back copies and staged writes, in the data dir.
JOURNAL_FILE, BACKUPS_DIR, STAGING_DIR = "library.sqlite", "library-backups", "library-staging"

SCHEMA = """
CREATE TABLE IF NOT EXISTS scans (
  id TEXT PRIMARY KEY, folder TEXT NOT NULL, state TEXT NOT NULL, total INTEGER NOT NULL DEFAULT 0,
  done INTEGER NOT NULL DEFAULT 0, message TEXT, updated REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS photos (
  id INTEGER PRIMARY KEY, scan TEXT NOT NULL, path TEXT NOT NULL, size INTEGER NOT NULL,
  mtime_ns INTEGER NOT NULL, kind TEXT NOT NULL, result TEXT NOT NULL,
  decision TEXT, lat REAL, lon REAL, decided REAL, written TEXT, UNIQUE(scan, path)
);
CREATE INDEX IF NOT EXISTS scans_folder ON scans(folder);
CREATE INDEX IF NOT EXISTS photos_scan ON photos(scan, id);
CREATE TABLE IF NOT EXISTS writes (
  id INTEGER PRIMARY KEY, scan TEXT NOT NULL, photo INTEGER NOT NULL, mode TEXT NOT NULL, target TEXT NOT NULL,
  backup TEXT, after_sha TEXT, created REAL NOT NULL, undone REAL, before_sha TEXT
);
"""
#: PRAGMA user_version of the schema above. 1 keyed photos by path alone and kept no hash of a write's
#: result: such a journal is refused with a message rather than misread. 2 lacked ``writes.before_sha``,
#: which is added in place. A newer version is a newer program's: refused, never downgraded.
SCHEMA_VERSION = 3
#: The columns each table must have: a file of another layout is refused, not misread.
EXPECTED_COLUMNS = {
    "scans": {"id", "folder", "state", "total", "done", "message", "updated"},
    "photos": {"id", "scan", "path", "size", "mtime_ns", "kind", "result", "decision", "lat", "lon", "written"},
    "writes": {"id", "scan", "photo", "mode", "target", "backup", "after_sha", "created", "undone"},
}

#: What a photo of the library is: located (it had no GPS), a reference (it had GPS), or a problem file.
LOCATED, REFERENCE, PROBLEM = "located", "reference", "problem"
ACCEPTED, REJECTED = "accepted", "rejected"
COLUMNS = "id, scan, path, size, mtime_ns, kind, result, decision, lat, lon, written"


class JournalError(RuntimeError):
    """The journal file cannot be used: an older or newer layout, another program's file, not SQLite."""


def new_scan_id() -> str:
    """16 random hex digits: unguessable, and no path in URLs."""
    return secrets.token_hex(8)


@dataclass(frozen=True)
class PhotoRecord:
    id: int
    scan: str
    path: str
    size: int
    mtime_ns: int
    kind: str
    result: dict
    decision: str | None
    lat: float | None
    lon: float | None
    written: dict | None

    @property
    def accepted_position(self) -> tuple[float, float] | None:
        if self.decision == ACCEPTED and self.lat is not None and self.lon is not None:
            return self.lat, self.lon
        return None


class LibraryJournal:
    """See the module docstring. Open with ``LibraryJournal(data_dir)``; ``close`` when done."""

    def __init__(self, data_dir: Path):
        Path(data_dir).mkdir(parents=True, exist_ok=True)
        self.path = Path(data_dir) / JOURNAL_FILE
        self._db = sqlite3.connect(self.path, check_same_thread=False, timeout=30, isolation_level=None)
        try:
            self._open()
        except sqlite3.DatabaseError as e:  # random bytes, a damaged file: said, never a traceback
            self._db.close()
            raise JournalError(f"{self.path} is not a library journal ({e}): move it aside and scan again") from None
        except JournalError:
            self._db.close()
            raise
        self._lock = threading.RLock()

    def _open(self) -> None:
        """Check the file's layout, bring a version-2 journal up to date, make a new one."""
        self._db.execute("PRAGMA journal_mode=WAL")
        version = self._db.execute("PRAGMA user_version").fetchone()[0]
        tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if version > SCHEMA_VERSION:
            raise JournalError(
                f"{self.path} was written by a newer version (layout {version}, this one reads up to "
                f"{SCHEMA_VERSION}): run that version, or move the file aside"
            )
        if "photos" in tables and version < 2:
            raise JournalError(f"{self.path} is an older library journal: move it aside and scan again")
        for table in tables & set(EXPECTED_COLUMNS):
            have = {r[1] for r in self._db.execute(f"PRAGMA table_info({table})")}
            if not EXPECTED_COLUMNS[table] <= have:
                raise JournalError(f"{self.path} is not a library journal of a known layout: move it aside")
        if version == 2:
            self._db.execute("ALTER TABLE writes ADD COLUMN before_sha TEXT")
        self._db.executescript(SCHEMA)
        self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")

    def close(self) -> None:
        self._db.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    # -- scans ------------------------------------------------------------------------------------------
    def scan_of(self, folder: Path) -> str | None:
        """The id of the scan of ``folder`` (resolved), or None if it was never scanned into this journal."""
        with self._lock:
            got = self._db.execute("SELECT id FROM scans WHERE folder=?", (str(Path(folder).resolve()),)).fetchone()
        return got[0] if got else None

    def scan_id_of(self, folder: Path) -> str | None:
        """``scan_of`` under its first name (bench/library_time_prior.py calls it)."""
        return self.scan_of(folder)

    def start_scan(self, folder: Path, total: int) -> str:
        """Mark the scan of ``folder`` running (made, with a new random id, on its first scan); its id."""
        name = str(Path(folder).resolve())
        with self._tx() as db:
            got = db.execute("SELECT id FROM scans WHERE folder=?", (name,)).fetchone()
            sid = got[0] if got else new_scan_id()
            db.execute(
                "INSERT INTO scans(id, folder, state, total, done, message, updated) VALUES (?,?,?,?,0,NULL,?) "
                "ON CONFLICT(id) DO UPDATE SET state=excluded.state, total=excluded.total, done=0, message=NULL, "
                "updated=excluded.updated",
                (sid, name, "running", total, time.time()),
            )
        return sid

    def interrupt_running(self) -> list[str]:
        """Mark every scan still "running" as interrupted: at a server's start no thread of this process runs
        one, so such a scan died with an earlier process (killed, crashed). Its journalled photos stay; the
        next scan of its folder does the rest. Returns their ids."""
        with self._tx() as db:
            ids = [r[0] for r in db.execute("SELECT id FROM scans WHERE state='running'").fetchall()]
            db.execute(
                "UPDATE scans SET state='interrupted', message=?, updated=? WHERE state='running'",
                ("the process running this scan stopped before it finished: scan again to resume", time.time()),
            )
        return ids

    def progress(self, sid: str, done: int) -> None:
        with self._tx() as db:
            db.execute("UPDATE scans SET done=?, updated=? WHERE id=?", (done, time.time(), sid))

    def finish_scan(self, sid: str, state: str, message: str | None) -> None:
        with self._tx() as db:
            db.execute("UPDATE scans SET state=?, message=?, updated=? WHERE id=?", (state, message, time.time(), sid))

    def scan(self, sid: str) -> dict | None:
        with self._lock:
            row = self._db.execute("SELECT id, folder, state, total, done, message FROM scans WHERE id=?", (sid,))
            got = row.fetchone()
        if got is None:
            return None
        return dict(zip(("id", "folder", "state", "total", "done", "message"), got, strict=True))

    # -- photos -----------------------------------------------------------------------------------------
    def known(self, sid: str) -> dict[str, PhotoRecord]:
        """Every photo journalled for this library, by path."""
        return {r.path: r for r in self.photos(sid)}

    def located_paths(self) -> set[str]:
        """Every photo that a library of this journal located (whatever its scan): such a photo holds, at
        most, a position this service guessed and the user accepted, never a measured one."""
        with self._lock:
            rows = self._db.execute("SELECT DISTINCT path FROM photos WHERE kind=?", (LOCATED,)).fetchall()
        return {r[0] for r in rows}

    def record(self, sid: str, path: Path, size: int, mtime_ns: int, kind: str, result: dict) -> None:
        """A photo's (new) suggestion: a file that changed since its decision loses the decision."""
        with self._tx() as db:
            db.execute(
                "INSERT INTO photos(scan, path, size, mtime_ns, kind, result) VALUES (?,?,?,?,?,?) "
                "ON CONFLICT(scan, path) DO UPDATE SET size=excluded.size, "
                "mtime_ns=excluded.mtime_ns, kind=excluded.kind, result=excluded.result, decision=NULL, "
                "lat=NULL, lon=NULL, decided=NULL",
                (sid, str(path), size, mtime_ns, kind, json.dumps(result)),
            )

    def restat(self, photo_id: int, size: int, mtime_ns: int) -> None:
        """After our own in-file write: the file changed, but not its suggestion or decision."""
        with self._tx() as db:
            db.execute("UPDATE photos SET size=?, mtime_ns=? WHERE id=?", (size, mtime_ns, photo_id))

    def photos(self, sid: str, kind: str | None = None) -> list[PhotoRecord]:
        sql = f"SELECT {COLUMNS} FROM photos WHERE scan=?"
        args: tuple = (sid,)
        if kind is not None:
            sql, args = sql + " AND kind=?", (sid, kind)
        with self._lock:
            rows = self._db.execute(sql + " ORDER BY path", args).fetchall()
        return [_record(r) for r in rows]

    def photo(self, sid: str, photo_id: int) -> PhotoRecord | None:
        with self._lock:
            row = self._db.execute(
                f"SELECT {COLUMNS} FROM photos WHERE scan=? AND id=?",
                (sid, photo_id),
            ).fetchone()
        return _record(row) if row else None

    def decide(self, photo_id: int, decision: str | None, lat: float | None, lon: float | None) -> None:
        with self._tx() as db:
            db.execute(
                "UPDATE photos SET decision=?, lat=?, lon=?, decided=? WHERE id=?",
                (decision, lat, lon, time.time() if decision else None, photo_id),
            )

    def set_written(self, photo_id: int, written: dict | None) -> None:
        with self._tx() as db:
            db.execute(
                "UPDATE photos SET written=? WHERE id=?", (None if written is None else json.dumps(written), photo_id)
            )

    # -- writes (for undo) ------------------------------------------------------------------------------
    def add_write(
        self,
        sid: str,
        photo_id: int,
        mode: str,
        target: Path,
        backup: Path | None,
        before_sha: str | None,
        after_sha: str,
    ) -> int:
        """Record a write before the target is replaced: its backup (None: the target is new), the SHA-256
        of the target before (None: it did not exist) and of what the write is about to leave. So after a
        crash at any point undo knows the file's state: as before (nothing to undo), as written (restore
        it), or anything else (changed since, by the user or another tool: never overwritten)."""
        with self._tx() as db:
            cur = db.execute(
                "INSERT INTO writes(scan, photo, mode, target, backup, before_sha, after_sha, created) "
                "VALUES (?,?,?,?,?,?,?,?)",
                (sid, photo_id, mode, str(target), None if backup is None else str(backup), before_sha, after_sha,
                 time.time()),
            )  # fmt: skip
            return int(cur.lastrowid)

    def live_writes(self, sid: str, photo_id: int | None = None) -> list[dict]:
        """Writes not undone (of one photo, or all), newest first (undo walks back in time)."""
        sql = (
            "SELECT id, photo, mode, target, backup, before_sha, after_sha FROM writes WHERE scan=? AND undone IS NULL"
        )
        args: tuple = (sid,)
        if photo_id is not None:
            sql, args = sql + " AND photo=?", (sid, photo_id)
        with self._lock:
            rows = self._db.execute(sql + " ORDER BY id DESC", args).fetchall()
        keys = ("id", "photo", "mode", "target", "backup", "before_sha", "after_sha")
        return [dict(zip(keys, r, strict=True)) for r in rows]

    def mark_undone(self, write_id: int) -> None:
        with self._tx() as db:
            db.execute("UPDATE writes SET undone=? WHERE id=?", (time.time(), write_id))


def copy_journal(journal: Path, dest: Path) -> None:
    """A consistent copy of the journal file at ``dest``, through SQLite's backup API (it is in WAL mode and
    a scan or a review may be writing it: a file copy could miss the -wal's pages or tear). A file that is
    not SQLite (damaged) is copied byte for byte: opening it says what is wrong, as it does here."""
    try:
        with closing(sqlite3.connect(journal, timeout=30)) as src, closing(sqlite3.connect(dest)) as dst:
            src.backup(dst)
    except sqlite3.DatabaseError:
        Path(dest).unlink(missing_ok=True)
        shutil.copy2(journal, dest)


def rebase_backups(journal: Path, backups: Path) -> int:
    """Point every write's backup at the file of the same name in ``backups`` (a journal restored into
    another data dir names the copies of the one it was made in); returns how many rows changed, 0 for a
    file that is not a journal (restored as it was: opening it says what is wrong)."""
    try:
        with closing(sqlite3.connect(journal, timeout=30)) as db, db:
            rows = db.execute("SELECT id, backup FROM writes WHERE backup IS NOT NULL").fetchall()
            moved = [(str(backups / Path(old).name), i) for i, old in rows if str(backups / Path(old).name) != old]
            db.executemany("UPDATE writes SET backup=? WHERE id=?", moved)
    except sqlite3.DatabaseError:
        return 0
    return len(moved)


def _record(row) -> PhotoRecord:
    rid, sid, path, size, mtime_ns, kind, result, decision, lat, lon, written = row
    done = json.loads(written) if written else None
    return PhotoRecord(rid, sid, path, size, mtime_ns, kind, json.loads(result), decision, lat, lon, done)
