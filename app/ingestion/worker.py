"""The ingestion worker: encodes pending references in batches through the core.

Accepted uploads are committed as ``pending`` rows with their image on disk before the API answers 202:
those rows are the durable queue. The worker encodes a batch and completes it in one transaction (which
also appends the index changes to the log); completing is idempotent, so a worker killed at any moment
loses nothing and duplicates nothing. Only one worker runs per data dir (a file lock; on PostgreSQL, per
database, across hosts: an advisory lock), and the process that holds it is also the one that writes index
snapshots (the writer role: ``app.ingestion.writer``).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from app.ingestion.completion import complete, encode_batch
from app.storage.backend import StorageBackend, WriterLock
from app.storage.errors import is_storage_error
from app.usecases.service import GeolocService

log = logging.getLogger("geoloc.worker")


def writer_lock(backend: StorageBackend) -> WriterLock:
    """The lock that makes one process the writer: the storage backend's (the data dir's lock file on
    SQLite, the database's advisory lock on PostgreSQL): the backend the process made from its Settings, so
    that the lock is where the rows are."""
    return backend.writer_lock()


class IngestWorker:
    def __init__(
        self,
        service: GeolocService,
        batch_size: int = 8,
        poll_seconds: float = 0.3,
        on_batch: Callable[[int, int], None] | None = None,
        workers: int = 1,
        max_attempts: int = 3,
    ):
        self.service = service
        self.batch_size = batch_size
        self.max_attempts = max_attempts  # started this often and never finished: quarantined
        self.poll_seconds = poll_seconds
        self.on_batch = on_batch  # (indexed, failed) -> None, for metrics and progress
        self.workers = workers
        self.wake = threading.Event()
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self.retrying = False  # the last batch could not be read (storage): back off before the next try

    def run_once(self) -> int:
        """Encode one batch of pending references; returns how many rows it completed (0: idle or retrying)."""
        store = self.service.store
        batch = store.pending(self.batch_size)
        if not batch:
            return 0
        # A row whose last encoding never finished (the process died meanwhile) goes alone: should it take the
        # process down again, it takes no other row with it, and after max_attempts it is quarantined.
        suspects = store.attempts([i for i, _ in batch])
        if suspects:
            batch = [next(b for b in batch if b[0] in suspects)]
            log.warning("reference %d: its last encoding never finished; encoding it alone", batch[0][0])
        quarantined = store.start_attempts([i for i, _ in batch], self.max_attempts)
        if quarantined:
            log.error(
                "quarantined references %s: their encoding never finished %d times", quarantined, self.max_attempts
            )
            batch = [b for b in batch if b[0] not in quarantined]
        results = encode_batch(self.service, batch, self.workers)
        store.end_attempts([i for i, _ in batch])  # they returned: only a death leaves a count behind
        done = complete(self.service, results)
        failed = sum(1 for r in results if r.error is not None) + len(quarantined)
        retry = sum(1 for r in results if r.retry)
        if self.on_batch:
            self.on_batch(len(done), failed)
        log.info("encoded %d references (%d failed, %d left queued for a storage retry)", len(done), failed, retry)
        self.retrying = bool(results) and retry == len(results)
        return len(results) - retry + len(quarantined)

    def run_forever(self) -> None:
        """Encode until stopped. The rest of the writer role (snapshots, housekeeping) runs beside it in
        threads of its own, started and stopped by ``app.ingestion.writer.Writer``."""
        backoff = self.poll_seconds
        while not self.stop_event.is_set():
            try:
                handled = self.run_once()
                backoff = min(max(backoff * 2, 1.0), 30.0) if self.retrying else self.poll_seconds
            except Exception as e:  # keep serving: a batch that failed is retried after a pause
                if is_storage_error(e):
                    log.warning("ingestion paused: %s", e)
                else:
                    log.exception("ingestion batch failed")
                handled = 0
                backoff = min(max(backoff * 2, 1.0), 30.0)
            if not handled:
                self.wake.wait(backoff)
                self.wake.clear()

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run_forever, name="geoloc-ingest", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        self.stop_event.set()
        self.wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
