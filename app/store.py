"""The data directory: SQLite metadata and codes (the source of truth), stored images, FAISS snapshots.

Why this split: SQLite in WAL mode gives durable, atomic commits, so a reference accepted is a row that
survives a crash; the codes live in that same row, so the FAISS indexes are only a cache that can always
be rebuilt from them. Snapshots of the indexes are written atomically with a manifest naming the version
of the metadata they reflect; a stale or missing snapshot is rebuilt on open, never trusted.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine.artifacts import atomic_write_bytes
from app.engine.errors import IncompatibleArtifact
from app.engine.pipeline import Pipeline
from app.engine.search import ReferenceIndex

DB_NAME = "references.sqlite"
SNAPSHOT_MANIFEST = "index.json"
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
"""


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


def sha256_of(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class ReferenceStore:
    """One data directory bound to one fitted pipeline (its fingerprint is recorded on first use)."""

    def __init__(self, data_dir: Path):
        self.data_dir = Path(data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        (self.data_dir / "images").mkdir(exist_ok=True)
        self._lock = threading.RLock()
        self.db = sqlite3.connect(self.data_dir / DB_NAME, check_same_thread=False, isolation_level=None)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=FULL")
        self.db.execute("PRAGMA busy_timeout=10000")
        self.db.executescript(SCHEMA)

    def close(self) -> None:
        self.db.close()

    # -- meta -----------------------------------------------------------------------------------------
    def get_meta(self, key: str) -> str | None:
        row = self.db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return row[0] if row else None

    def set_meta(self, key: str, value: str) -> None:
        self.db.execute(
            "INSERT INTO meta(key, value) VALUES(?, ?) ON CONFLICT(key) DO UPDATE SET value=excluded.value",
            (key, value),
        )

    def bind(self, pipeline: Pipeline) -> None:
        """Record which fitted pipeline encoded this collection; refuse a different one."""
        fp = self.get_meta("fingerprint")
        if fp is None:
            self.set_meta("fingerprint", pipeline.fingerprint)
            self.set_meta("config", pipeline.config.name)
        elif fp != pipeline.fingerprint and self.count() > 0:
            raise IncompatibleArtifact(
                f"{self.data_dir} holds codes from pipeline {fp}, not {pipeline.fingerprint}: use the models dir "
                "and --config the collection was built with, or start a new --data-dir"
            )
        else:
            self.set_meta("fingerprint", pipeline.fingerprint)
            self.set_meta("config", pipeline.config.name)

    @property
    def version(self) -> int:
        """Bumped on every change of the collection: snapshots and readers compare against it."""
        return int(self.get_meta("version") or 0)

    def _bump(self) -> None:
        self.db.execute(
            "INSERT INTO meta(key, value) VALUES('version', '1') ON CONFLICT(key) DO UPDATE SET "
            "value=CAST(value AS INTEGER) + 1"
        )

    # -- references -----------------------------------------------------------------------------------
    def find_by_sha(self, sha: str) -> int | None:
        row = self.db.execute("SELECT id FROM refs WHERE sha256=?", (sha,)).fetchone()
        return row[0] if row else None

    def add(
        self,
        image_bytes: bytes,
        ext: str,
        lat: float,
        lon: float,
        float_code: np.ndarray | None,
        binary_code: np.ndarray | None,
        heading: float | None = None,
        captured_at: str | None = None,
        label: str | None = None,
        source: str | None = None,
        pending: bool = False,
    ) -> tuple[int, bool]:
        """Store one reference; returns (id, created). Identical bytes return the existing id.
        ``pending``: accepted now, encoded later by the worker (the image is on disk, the row committed)."""
        sha = sha256_of(image_bytes)
        with self._lock:
            existing = self.find_by_sha(sha)
            if existing is not None:
                return existing, False
            image_path = self.data_dir / "images" / f"{sha}.{ext}"
            if not image_path.exists():
                atomic_write_bytes(image_path, image_bytes)
            self.db.execute("BEGIN IMMEDIATE")
            try:
                cur = self.db.execute(
                    "INSERT INTO refs(sha256, lat, lon, heading, captured_at, label, source, image_ext, created_at, "
                    "float_code, binary_code, status) VALUES(?,?,?,?,?,?,?,?,?,?,?,?)",
                    (
                        sha,
                        lat,
                        lon,
                        heading,
                        captured_at,
                        label,
                        source,
                        ext,
                        time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                        None if float_code is None else np.asarray(float_code, np.float32).tobytes(),
                        None if binary_code is None else np.asarray(binary_code, np.uint8).tobytes(),
                        "pending" if pending else "indexed",
                    ),
                )
                self._bump()
                self.db.execute("COMMIT")
            except BaseException:
                self.db.execute("ROLLBACK")
                raise
            return int(cur.lastrowid), True

    def delete(self, ref_id: int) -> bool:
        with self._lock:
            row = self.db.execute("SELECT sha256, image_ext FROM refs WHERE id=?", (ref_id,)).fetchone()
            if row is None:
                return False
            self.db.execute("BEGIN IMMEDIATE")
            self.db.execute("DELETE FROM refs WHERE id=?", (ref_id,))
            self._bump()
            self.db.execute("COMMIT")
            (self.data_dir / "images" / f"{row[0]}.{row[1]}").unlink(missing_ok=True)
            return True

    def get(self, ref_id: int) -> Reference | None:
        row = self.db.execute(f"SELECT {_COLS} FROM refs WHERE id=?", (ref_id,)).fetchone()
        return Reference(*row) if row else None

    def image_path(self, ref_id: int) -> Path | None:
        row = self.db.execute("SELECT sha256, image_ext FROM refs WHERE id=?", (ref_id,)).fetchone()
        return self.data_dir / "images" / f"{row[0]}.{row[1]}" if row else None

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

    def ids_in_bbox(self, bbox: tuple[float, float, float, float]) -> np.ndarray:
        min_lon, min_lat, max_lon, max_lat = bbox
        rows = self.db.execute(
            "SELECT id FROM refs WHERE lat BETWEEN ? AND ? AND lon BETWEEN ? AND ?",
            (min_lat, max_lat, min_lon, max_lon),
        ).fetchall()
        return np.array([r[0] for r in rows], np.int64)

    def count(self, status: str | None = "indexed") -> int:
        """References in the index (by default), or of another status, or all (None)."""
        if status is None:
            return self.db.execute("SELECT COUNT(*) FROM refs").fetchone()[0]
        return self.db.execute("SELECT COUNT(*) FROM refs WHERE status=?", (status,)).fetchone()[0]

    # -- the ingestion queue: pending rows are the durable queue ---------------------------------------
    def pending(self, limit: int) -> list[tuple[int, Path]]:
        rows = self.db.execute(
            "SELECT id, sha256, image_ext FROM refs WHERE status='pending' ORDER BY id LIMIT ?", (limit,)
        ).fetchall()
        return [(r[0], self.data_dir / "images" / f"{r[1]}.{r[2]}") for r in rows]

    def complete(self, results: list[tuple[int, np.ndarray | None, np.ndarray | None, str | None]]) -> list[int]:
        """Record encoded codes (or an error) for pending rows, in one transaction; return the ids that
        became indexed. Rows deleted meanwhile are skipped, and re-running a batch changes nothing:
        completing is idempotent, so a worker killed anywhere can simply start again."""
        done = []
        with self._lock:
            self.db.execute("BEGIN IMMEDIATE")
            try:
                for ref_id, fcode, bcode, error in results:
                    if error is not None:
                        self.db.execute(
                            "UPDATE refs SET status='failed', error=? WHERE id=? AND status='pending'", (error, ref_id)
                        )
                        continue
                    cur = self.db.execute(
                        "UPDATE refs SET float_code=?, binary_code=?, status='indexed' WHERE id=? AND status='pending'",
                        (
                            None if fcode is None else np.asarray(fcode, np.float32).tobytes(),
                            None if bcode is None else np.asarray(bcode, np.uint8).tobytes(),
                            ref_id,
                        ),
                    )
                    if cur.rowcount:
                        done.append(ref_id)
                self._bump()
                self.db.execute("COMMIT")
            except BaseException:
                self.db.execute("ROLLBACK")
                raise
        return done

    def create_job(self, items: list[tuple[int, bool]]) -> str:
        job_id = uuid.uuid4().hex
        with self._lock:
            self.db.execute("BEGIN IMMEDIATE")
            self.db.execute(
                "INSERT INTO jobs(id, created_at) VALUES(?, ?)",
                (job_id, time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())),
            )
            self.db.executemany(
                "INSERT INTO job_items(job_id, position, ref_id, duplicate) VALUES(?,?,?,?)",
                [(job_id, n, ref_id, int(dup)) for n, (ref_id, dup) in enumerate(items)],
            )
            self.db.execute("COMMIT")
        return job_id

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

    def positions(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ids = [int(i) for i in ids]
        if not ids:
            return np.zeros(0), np.zeros(0)
        q = ",".join("?" * len(ids))
        found = {r[0]: (r[1], r[2]) for r in self.db.execute(f"SELECT id, lat, lon FROM refs WHERE id IN ({q})", ids)}
        pos = np.array([found.get(i, (np.nan, np.nan)) for i in ids], np.float64)
        return pos[:, 0], pos[:, 1]

    def all_codes(self) -> tuple[np.ndarray, list[bytes | None], list[bytes | None]]:
        rows = self.db.execute(
            "SELECT id, float_code, binary_code FROM refs WHERE status='indexed' ORDER BY id"
        ).fetchall()
        return np.array([r[0] for r in rows], np.int64), [r[1] for r in rows], [r[2] for r in rows]

    # -- the FAISS cache ------------------------------------------------------------------------------
    def build_index(self, pipeline: Pipeline) -> ReferenceIndex:
        """The index for the current version: from the snapshot when it matches, else rebuilt from codes."""
        index = ReferenceIndex(pipeline.config, pipeline.float_dim, pipeline.bits)
        manifest_path = self.data_dir / SNAPSHOT_MANIFEST
        version = self.version
        if manifest_path.exists():
            m = json.loads(manifest_path.read_text())
            if m.get("version") == version and m.get("fingerprint") == pipeline.fingerprint:
                try:
                    if index.float is not None:
                        index.float.load_bytes((self.data_dir / m["float_file"]).read_bytes(), m["float_tombstones"])
                    if index.binary is not None:
                        index.binary.load_bytes((self.data_dir / m["binary_file"]).read_bytes(), m["binary_tombstones"])
                    if index.size == self.count():
                        return index
                except (OSError, KeyError, RuntimeError):
                    pass  # another process replaced the snapshot meanwhile, or it is damaged: rebuild
                index = ReferenceIndex(pipeline.config, pipeline.float_dim, pipeline.bits)
        ids, fcodes, bcodes = self.all_codes()
        if len(ids):
            f = np.stack([np.frombuffer(c, np.float32) for c in fcodes]) if index.float is not None else None
            b = np.stack([np.frombuffer(c, np.uint8) for c in bcodes]) if index.binary is not None else None
            index.add(ids, f, b)
        self.save_snapshot(index, pipeline, version)
        return index

    def save_snapshot(self, index: ReferenceIndex, pipeline: Pipeline, version: int) -> None:
        """Index files first (named by version, so a reader never pairs a manifest with files of another
        version), manifest last: a crash in between leaves a manifest naming an older version, which the next
        open detects and rebuilds. Files of older versions are removed afterwards."""
        files = {}
        for kind, idx in (("float", index.float), ("binary", index.binary)):
            if idx is not None:
                files[kind] = f"{kind}-v{version}.faiss"
                atomic_write_bytes(self.data_dir / files[kind], idx.to_bytes())
        manifest = {
            "float_file": files.get("float"),
            "binary_file": files.get("binary"),
            "version": version,
            "size": index.size,
            "config": pipeline.config.name,
            "fingerprint": pipeline.fingerprint,
            "float_dim": pipeline.float_dim,
            "bits": pipeline.bits,
            "float_tombstones": sorted(index.float.tombstones) if index.float is not None else [],
            "binary_tombstones": sorted(index.binary.tombstones) if index.binary is not None else [],
            "written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        atomic_write_bytes(self.data_dir / SNAPSHOT_MANIFEST, json.dumps(manifest, indent=1).encode())
        for old in self.data_dir.glob("*-v*.faiss"):
            if old.name not in files.values():
                try:
                    if int(old.stem.rsplit("-v", 1)[1]) < version:
                        old.unlink(missing_ok=True)
                except ValueError:
                    pass
