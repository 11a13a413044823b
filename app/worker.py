"""The live collection (an index kept current across processes) and the ingestion worker.

Accepted uploads are committed as ``pending`` rows with their image on disk before the API answers 202:
those rows are the durable queue. The worker encodes pending rows in batches and completes them in one
transaction; completing is idempotent, so a worker killed at any moment loses nothing and duplicates
nothing, and the next worker picks up the same rows. Only one worker runs per data dir (a file lock);
every process notices changes made by others through the collection's version number and reloads.
"""

from __future__ import annotations

import fcntl
import logging
import os
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np

from app.engine.errors import GeolocError
from app.engine.imageio import ImageLimits, load_image
from app.engine.pipeline import Pipeline, load_pipeline
from app.engine.search import ReferenceIndex
from app.store import ReferenceStore

log = logging.getLogger("geoloc.worker")


class LiveCollection:
    """The data dir as one process sees it: store, fitted pipeline, and the index of the current version.
    Searches and in-place changes of the index take ``lock``; a reload swaps in a new index object."""

    def __init__(self, data_dir: Path, models_dir: Path, config: str, limits: ImageLimits | None = None):
        self.store = ReferenceStore(data_dir)
        name = self.store.get_meta("config") or config
        self.pipeline: Pipeline = load_pipeline(models_dir, name)
        self.store.bind(self.pipeline)
        self.limits = limits or ImageLimits()
        self.lock = threading.RLock()
        self.version = self.store.version
        self.index: ReferenceIndex = self.store.build_index(self.pipeline)

    def current(self) -> ReferenceIndex:
        """The index, reloaded first if another process (or thread) changed the collection."""
        if self.store.version != self.version:
            with self.lock:
                v = self.store.version
                if v != self.version:
                    self.index = self.store.build_index(self.pipeline)
                    self.version = v
        return self.index

    def apply(self, change: Callable[[ReferenceIndex], None], version_before: int) -> None:
        """Apply our own committed change to the live index in place and snapshot it. If somebody else
        changed the collection in between, skip: the next ``current()`` reloads everything."""
        with self.lock:
            if version_before != self.version:
                return
            change(self.index)
            v = self.store.version
            self.store.save_snapshot(self.index, self.pipeline, v)
            self.version = v

    def delete(self, ref_id: int) -> bool:
        self.current()
        before = self.version
        if not self.store.delete(ref_id):
            return False
        if self.store.version == before + 1:
            self.apply(lambda idx: idx.remove([ref_id]), before)
        return True


class WorkerLock:
    """One ingestion worker per data dir: a second one would encode the same rows twice."""

    def __init__(self, data_dir: Path):
        self.path = Path(data_dir) / "worker.lock"
        self._fd: int | None = None

    def acquire(self) -> bool:
        fd = os.open(self.path, os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            return False
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        self._fd = fd
        return True

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


class IngestWorker:
    def __init__(
        self,
        live: LiveCollection,
        batch_size: int = 8,
        poll_seconds: float = 0.3,
        on_batch: Callable[[int, int], None] | None = None,
    ):
        self.live = live
        self.batch_size = batch_size
        self.poll_seconds = poll_seconds
        self.on_batch = on_batch  # (indexed, failed) -> None, for metrics
        self.wake = threading.Event()
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None

    def _encode(self, ref_id: int, path: Path) -> tuple[int, np.ndarray | None, np.ndarray | None, str | None]:
        try:
            img = load_image(path.read_bytes(), self.live.limits)
            codes = self.live.pipeline.encode_image(img.rgb)
            return ref_id, codes.float_, codes.binary, None
        except FileNotFoundError:
            return ref_id, None, None, "the stored image is missing"
        except GeolocError as e:
            return ref_id, None, None, str(e)

    def run_once(self) -> int:
        """Encode one batch of pending references; returns how many rows it handled."""
        store = self.live.store
        batch = store.pending(self.batch_size)
        if not batch:
            return 0
        results = [self._encode(ref_id, path) for ref_id, path in batch]
        self.live.current()
        before = self.live.version
        done = store.complete(results)
        if done:
            by_id = {r[0]: r for r in results}
            ids = np.array(done, np.int64)
            f = np.stack([by_id[i][1] for i in done]) if self.live.index.float is not None else None
            b = np.stack([by_id[i][2] for i in done]) if self.live.index.binary is not None else None
            if store.version == before + 1:
                self.live.apply(lambda idx: idx.add(ids, f, b), before)
        failed = sum(1 for r in results if r[3] is not None)
        if self.on_batch:
            self.on_batch(len(done), failed)
        log.info("encoded %d references (%d failed)", len(done), failed)
        return len(batch)

    def run_forever(self) -> None:
        while not self.stop_event.is_set():
            try:
                handled = self.run_once()
            except Exception:  # keep serving: a bad batch is retried after a pause
                log.exception("ingestion batch failed")
                handled = 0
            if not handled:
                self.wake.wait(self.poll_seconds)
                self.wake.clear()

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run_forever, name="geoloc-ingest", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        self.stop_event.set()
        self.wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
