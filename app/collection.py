"""The collection as one process sees it: the store, the fitted pipeline, and a live index kept current.

Why it is built this way (cost per change independent of the collection's size):
- The index is loaded once (a verified snapshot plus the change log after it, or, when no snapshot can be
  trusted, a full rebuild from the codes in SQLite) and then only *caught up*: before each search the
  process compares the log's last version with the one it holds (one indexed SQL read) and applies exactly
  the changes in between, adds in place and deletions as tombstones.
- Snapshots are written by one process only (the one holding the worker lock), in the background, by the
  policy below: on a copy of the index taken under the lock (a memory copy), compacted and written to disk
  with the lock released, then swapped in after replaying what arrived meanwhile. Searches never wait for
  a disk write.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine.pipeline import Pipeline, load_pipeline
from app.engine.search import ReferenceIndex
from app.snapshots import SnapshotInvalid, load_snapshot, write_snapshot
from app.store import Change, ReferenceStore

log = logging.getLogger("geoloc.collection")


@dataclass(frozen=True)
class SnapshotPolicy:
    """Write a snapshot after ``every_changes`` index changes, or ``every_seconds`` after the first change
    not yet in one, and at a clean shutdown. A restart then replays at most that many changes."""

    every_changes: int = 5_000
    every_seconds: float = 300.0

    def due(self, pending_changes: int, seconds_pending: float) -> bool:
        """``seconds_pending``: since the oldest change not yet in a snapshot."""
        return pending_changes >= self.every_changes or (pending_changes > 0 and seconds_pending >= self.every_seconds)


@dataclass
class IndexStats:
    """What /metrics reports about the index's upkeep in this process."""

    full_rebuilds: int = 0
    replayed_at_start: int = 0
    snapshot_writes: int = 0
    snapshot_version: int | None = None
    snapshot_written_at: float | None = None  # wall time of the snapshot loaded or last written
    changes_applied: int = 0


def apply_changes(index: ReferenceIndex, changes: list[Change]) -> None:
    """Apply log entries in order: runs of adds in one call each, deletions as tombstones. An add whose row
    is gone (deleted since; its delete entry is in the same read) is skipped, and so is that delete."""
    skipped: set[int] = set()
    run: list[Change] = []

    def flush() -> None:
        if not run:
            return
        ids = np.array([c.ref_id for c in run], np.int64)
        f = np.stack([np.frombuffer(c.float_code, np.float32) for c in run]) if index.float is not None else None
        b = np.stack([np.frombuffer(c.binary_code, np.uint8) for c in run]) if index.binary is not None else None
        index.add(ids, f, b)
        run.clear()

    for c in changes:
        if c.op == "move":  # positions live in SQLite, read at every search: nothing to change in the index
            continue
        if c.op == "add":
            if c.float_code is None and c.binary_code is None:
                skipped.add(c.ref_id)
            else:
                run.append(c)
        else:
            flush()
            if c.ref_id not in skipped:
                index.remove([c.ref_id])
    flush()


def index_from_codes(pipeline: Pipeline, ids: np.ndarray, fcodes: list, bcodes: list) -> ReferenceIndex:
    index = ReferenceIndex(pipeline.config, pipeline.float_dim, pipeline.bits)
    if len(ids):
        f = np.stack([np.frombuffer(c, np.float32) for c in fcodes]) if index.float is not None else None
        b = np.stack([np.frombuffer(c, np.uint8) for c in bcodes]) if index.binary is not None else None
        index.add(ids, f, b)
    return index


class Collection:
    """One per process and data dir. ``search`` and every change of ``index`` hold ``lock``."""

    def __init__(self, store: ReferenceStore, pipeline: Pipeline, policy: SnapshotPolicy | None = None):
        self.store = store
        self.pipeline = pipeline
        self.policy = policy or SnapshotPolicy()
        self.lock = threading.RLock()
        self.stats = IndexStats()
        self._snapshot_lock = threading.Lock()
        self._first_pending_at: float | None = None  # when the oldest change not in a snapshot was applied
        self.rebuilt = False  # loaded by a full rebuild: a snapshot is due as soon as a writer can take it
        self.index, self.version = self._load()

    @classmethod
    def open(cls, data_dir: Path, models_dir: Path, config: str | None, policy: SnapshotPolicy | None = None):
        """The data dir's own configuration wins over ``config``: its codes were made by that pipeline."""
        store = ReferenceStore(data_dir)
        name = store.get_meta("config") or config or "hybrid"
        pipeline = load_pipeline(models_dir, name)
        store.bind(pipeline)
        return cls(store, pipeline, policy)

    # -- loading --------------------------------------------------------------------------------------
    def _load(self) -> tuple[ReferenceIndex, int]:
        try:
            index, manifest = load_snapshot(self.store.data_dir, self.pipeline)
        except SnapshotInvalid as e:
            if (self.store.data_dir / "index.json").exists():
                log.warning("snapshot not used (%s): rebuilding the index from the codes in SQLite", e)
            return self._rebuild()
        version = int(manifest["version"])
        changes = self.store.changes_since(version)
        apply_changes(index, changes)
        self.stats.replayed_at_start = len(changes)
        self.stats.snapshot_version = version
        self.stats.snapshot_written_at = float(manifest.get("written_at") or 0) or None
        log.info("index loaded from the snapshot of version %d and %d later changes", version, len(changes))
        return index, changes[-1].version if changes else version

    def _rebuild(self) -> tuple[ReferenceIndex, int]:
        t0 = time.perf_counter()
        version, ids, fcodes, bcodes = self.store.all_codes()
        index = index_from_codes(self.pipeline, ids, fcodes, bcodes)
        self.stats.full_rebuilds += 1
        self.rebuilt = True
        log.info("index rebuilt from %d stored codes in %.1f s", len(ids), time.perf_counter() - t0)
        return index, version

    # -- keeping current ------------------------------------------------------------------------------
    def catch_up(self) -> int:
        """Apply the changes other processes (or this one's worker) logged since our version; returns how many."""
        if self.store.version == self.version:
            return 0
        with self.lock:
            changes = self.store.changes_since(self.version)
            if not changes:
                return 0
            apply_changes(self.index, changes)
            self.version = changes[-1].version
            self.stats.changes_applied += len(changes)
            if self._first_pending_at is None:
                self._first_pending_at = time.time()
            return len(changes)

    @property
    def size(self) -> int:
        return self.index.size

    def check_mode(self, mode: str | None) -> str:
        return self.index.check_mode(mode)

    def search(self, float_code, binary_code, k: int, mode: str | None = None, allowed: np.ndarray | None = None):
        """``ReferenceIndex.search`` on the current index (caught up first, and safe against changes)."""
        self.catch_up()
        with self.lock:
            return self.index.search(float_code, binary_code, k, mode, allowed)

    # -- snapshots (only the process holding the worker lock calls these) ------------------------------
    def pending_changes(self) -> int:
        return self.version - (self.stats.snapshot_version or 0)

    def snapshot_due(self) -> bool:
        if self.rebuilt:
            return True
        pending = self.pending_changes()
        if pending and self._first_pending_at is None:  # replayed at start: count from then
            self._first_pending_at = time.time()
        waited = time.time() - self._first_pending_at if self._first_pending_at is not None else 0.0
        return self.policy.due(pending, waited)

    def write_snapshot(self) -> bool:
        """Copy under the lock, compact and write without it, then swap the compacted copy in (after
        replaying whatever was applied meanwhile). Returns False when there was nothing to write."""
        with self._snapshot_lock:
            self.catch_up()
            with self.lock:
                if self.stats.snapshot_version == self.version and not self.rebuilt:
                    return False
                v0 = self.version
                parts = {
                    k: (idx.to_bytes(), set(idx.tombstones))
                    for k, idx in (("float", self.index.float), ("binary", self.index.binary))
                    if idx is not None
                }
            copy = ReferenceIndex(self.pipeline.config, self.pipeline.float_dim, self.pipeline.bits)
            for k, (data, tombs) in parts.items():
                getattr(copy, k).load_bytes(data, tombs)
            del parts
            copy.compact()
            t0 = time.perf_counter()
            manifest = write_snapshot(self.store.data_dir, copy, self.pipeline, v0)
            with self.lock:
                later = [c for c in self.store.changes_since(v0) if c.version <= self.version]
                apply_changes(copy, later)
                self.index = copy
                self.rebuilt = False
            self.stats.snapshot_writes += 1
            self.stats.snapshot_version = v0
            self._first_pending_at = time.time() if self.version > v0 else None
            self.stats.snapshot_written_at = manifest["written_at"]
            log.info(
                "snapshot of version %d written (%d references) in %.2f s", v0, copy.size, time.perf_counter() - t0
            )
            return True


class SnapshotWriter:
    """The background thread that writes snapshots by the policy, and a last one at a clean stop."""

    def __init__(self, collection: Collection, check_seconds: float = 2.0):
        self.collection = collection
        self.check_seconds = check_seconds
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def run(self) -> None:
        while not self._stop.wait(self.check_seconds):
            try:
                self.collection.catch_up()
                if self.collection.snapshot_due():
                    self.collection.write_snapshot()
            except Exception:  # a failed write is retried at the next check; the log still holds everything
                log.exception("snapshot write failed")

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="geoloc-snapshot", daemon=True)
        self._thread.start()

    def stop(self, final: bool = True) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(60)
        if final:
            try:
                self.collection.write_snapshot()
            except Exception:
                log.exception("final snapshot write failed")
