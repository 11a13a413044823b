"""The writer role of a data dir, held by one process at a time: encoding the queued uploads (the ingestion
worker), writing the index snapshots and the database checkpoints, and the housekeeping of image files
(``app.orphans.Janitor``). The data dir's worker lock (``worker.lock``; on PostgreSQL the database's advisory
lock, one for all hosts: ``app.ingestion.worker.writer_lock``) says which process holds it; that
process runs all of it, and gives it up in one order: the worker stops, the final snapshot and checkpoint
are written, then the lock is released (a process that takes it over next finds nothing to replay).

Who takes it, each through ``Writer``:
- an API server with GEOLOC_WORKER=inprocess (``start``); while another process holds the lock it retries
  every GEOLOC_WORKER_RETRY_SECONDS and takes the role over once that process is gone (failover);
- ``geoloc worker`` (``run``: in its main thread until SIGTERM or Ctrl-C; it refuses when the lock is held);
- ``geoloc ingest`` (``drain``: the rows earlier runs left pending, then the final snapshot; no threads);
- ``geoloc refit`` (``write_snapshot_if_free``: the new generation's snapshot when nobody holds the lock).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

from app.ingestion.worker import IngestWorker, writer_lock
from app.policies import IndexSizing
from app.storage.backend import StorageBackend
from app.storage.orphans import Janitor
from app.storage.sqlite import SqliteBackend
from app.usecases.collection import Collection, SnapshotWriter
from app.usecases.service import GeolocService

log = logging.getLogger("geoloc.worker")


class WriterBusy(Exception):
    """Another process holds the data dir's worker lock (``geoloc worker`` refuses to start)."""


class Writer:
    """One data dir's writer role in this process: ``start`` (threads, optionally with failover), ``run``
    (the calling thread), ``drain`` (one pass, no threads); ``stop`` in every case."""

    def __init__(
        self,
        backend: StorageBackend,
        batch: int = 8,
        workers: int = 1,
        on_batch: Callable[[int, int], None] | None = None,
        logger: logging.Logger = log,
        max_attempts: int = 3,
    ):
        self.lock = writer_lock(backend)
        self.batch = batch
        self.max_attempts = max_attempts  # GEOLOC_ENCODE_ATTEMPTS: see IngestWorker
        self.workers = workers
        self.on_batch = on_batch  # (indexed, failed) -> None, for metrics
        self.log = logger  # the messages of the role's owner (an API server logs them as geoloc.api)
        self.service: GeolocService | None = None
        self.collection: Collection | None = None  # what the final snapshot is written from
        self.worker: IngestWorker | None = None
        self.snapshots: SnapshotWriter | None = None
        self.janitor: Janitor | None = None
        self._stopping = threading.Event()
        self._watch: threading.Thread | None = None  # the failover thread, while another process holds the lock

    @property
    def held(self) -> bool:
        return self.lock.held

    def acquire(self) -> bool:
        """Take the lock if no other process holds it (never waits)."""
        return self.held or self.lock.acquire()

    def attach(self, service: GeolocService) -> None:
        """The service the role works for (``start``, ``run`` and ``drain`` attach theirs)."""
        self.service = service
        self.collection = service.collection

    def _worker(self, service: GeolocService) -> IngestWorker:
        return IngestWorker(
            service, self.batch, on_batch=self.on_batch, workers=self.workers, max_attempts=self.max_attempts
        )

    # -- in threads: an API server ----------------------------------------------------------------------
    def start(
        self,
        service: GeolocService,
        retry_seconds: float | None = None,
        on_started: Callable[[IngestWorker], None] | None = None,
    ) -> bool:
        """Take the lock and, holding it, start the ingestion worker, the snapshot writer and the janitor,
        then call ``on_started`` with the running worker. False when another process holds the lock: nothing
        runs then, and with ``retry_seconds`` a thread retries that often and starts everything once the
        holder is gone (its flock goes with it), until ``stop``."""
        self.attach(service)
        started = self._start_threads(on_started)
        if retry_seconds is not None and self.lock.can_be_lost:  # the database's lock: held, or not, for now
            self._watch = threading.Thread(
                target=self._supervise, args=(retry_seconds, on_started), name="geoloc-worker-failover", daemon=True
            )
            self._watch.start()
        elif retry_seconds is not None and not started:
            self._watch = threading.Thread(
                target=self._take_over, args=(retry_seconds, on_started), name="geoloc-worker-failover", daemon=True
            )
            self._watch.start()
        return started

    def _start_threads(self, on_started: Callable[[IngestWorker], None] | None) -> bool:
        if not self.acquire():
            return False
        assert self.service is not None and self.collection is not None
        self.collection.hold_writer_role(True)
        worker = self._worker(self.service)
        worker.start()
        self.janitor = Janitor(self.service.store).start()
        self.snapshots = SnapshotWriter(self.collection)
        self.snapshots.start()
        self.worker = worker
        if on_started is not None:  # last: everything runs by now
            on_started(worker)
        return True

    def _take_over(self, every: float, on_started: Callable[[IngestWorker], None] | None) -> None:
        """Failover: without it, uploads accepted by a process that did not hold the lock stayed queued
        after the holder died, until someone restarted a worker by hand."""
        while not self._stopping.wait(every):
            try:
                if self._start_threads(on_started):
                    self.log.warning(
                        "took over the worker lock (%s): this process now runs the ingestion worker",
                        self.lock.where,
                    )
                    return
            except Exception:  # an unreadable lock file now may be fine at the next try
                self.log.exception("taking over the worker lock failed; retrying in %.0f s", every)

    def _supervise(self, every: float, on_started: Callable[[IngestWorker], None] | None) -> None:
        """Failover on PostgreSQL, both ways: take the role once its holder's session is gone, and give it up
        when this process's own lock session is gone (the database restarted, or this host was cut off from
        it: another process may hold the role by now), then try to take it again. Without the second half a
        holder that lost its lock would keep writing snapshots beside the new holder."""
        while not self._stopping.wait(every):
            try:
                if not self.held:
                    if self._start_threads(on_started):
                        self.log.warning(
                            "took over the worker lock (%s): this process now runs the ingestion worker",
                            self.lock.where,
                        )
                elif not self.lock.alive():
                    self.log.error(
                        "lost the worker lock (%s): its database session ended; this process stops the worker "
                        "and tries to take the lock again",
                        self.lock.where,
                    )
                    self._stop_threads()
                    self.lock.release()
            except Exception:  # the database unreachable now may answer at the next try
                self.log.exception("taking over the worker lock failed; retrying in %.0f s", every)

    def _stop_threads(self) -> None:
        """The role's threads stopped, without a final snapshot (the role may be another process's now)."""
        if self.collection is not None:
            self.collection.hold_writer_role(False)
        if self.worker is not None:
            self.worker.stop()
            self.worker = None
        if self.janitor is not None:
            self.janitor.stop()
            self.janitor = None
        if self.snapshots is not None:
            self.snapshots.stop(final=False)
            self.snapshots = None

    # -- in the calling thread: `geoloc worker` -----------------------------------------------------------
    def run(self, service: GeolocService, retry_seconds: float | None = None) -> None:
        """Run the role in this thread until ``request_stop`` (a signal handler) or Ctrl-C, then ``stop``.
        The lock must be held (``acquire``). With a lock that can be lost under a running holder (the
        database's, on PostgreSQL) and ``retry_seconds``: every ``retry_seconds`` the lock's session is
        checked; once it is gone the role is given up as the in-process writer gives it up (the worker and
        the snapshot writer stop, no final snapshot: another process may hold the role by now), and the
        process waits to take it again, retrying as often."""
        if not self.held:
            raise RuntimeError(f"{self.lock.where} is not held by this process")
        self.attach(service)
        watch = retry_seconds is not None and self.lock.can_be_lost
        lost = False
        try:
            while not self._stopping.is_set():
                lost = self._run_held(service, retry_seconds if watch else None)
                if not lost or not self._wait_for_role(retry_seconds):
                    break
                lost = False
        except KeyboardInterrupt:
            pass
        finally:
            self.stop(final=not lost)

    def _run_held(self, service: GeolocService, check_every: float | None) -> bool:
        """The role's work while the lock is held; True when it ended because the lock's session was lost."""
        service.collection.hold_writer_role(True)
        self.worker = self._worker(service)
        self.snapshots = SnapshotWriter(service.collection)
        self.snapshots.start()
        self.janitor = Janitor(service.store).start()
        lost = threading.Event()
        done = threading.Event()
        checker = None
        if check_every is not None:
            checker = threading.Thread(
                target=self._check_lock, args=(check_every, lost, done), name="geoloc-worker-lock", daemon=True
            )
            checker.start()
        try:
            if not self._stopping.is_set():
                self.worker.run_forever()
        finally:
            done.set()
            if checker is not None:
                checker.join()
        if not lost.is_set():
            return False
        self._stop_threads()
        self.lock.release()
        return True

    def _check_lock(self, every: float, lost: threading.Event, done: threading.Event) -> None:
        """Beside ``run``: end the worker's run once this process's lock session is gone."""
        while not done.wait(every):
            if not self.lock.alive():
                self.log.error(
                    "lost the worker lock (%s): its database session ended; this worker stops and tries to "
                    "take the lock again",
                    self.lock.where,
                )
                lost.set()
                if self.worker is not None:
                    self.worker.stop_event.set()
                    self.worker.wake.set()
                return

    def _wait_for_role(self, every: float) -> bool:
        """After losing the lock: take it again once free; False when stopped meanwhile."""
        while not self._stopping.wait(every):
            try:
                if self.acquire():
                    self.log.warning("took over the worker lock (%s) again", self.lock.where)
                    return True
            except Exception:  # the database unreachable now may answer at the next try
                self.log.exception("taking the worker lock failed; retrying in %.0f s", every)
        return False

    def request_stop(self) -> None:
        """Make ``run`` return; only sets events, so a signal handler may call it."""
        self._stopping.set()
        if self.worker is not None:
            self.worker.stop_event.set()

    # -- one pass: `geoloc ingest` ------------------------------------------------------------------------
    def drain(self, service: GeolocService) -> int:
        """Holding the lock: encode the rows left pending (by crashed runs, or storage retries) until none is
        left, and return how many; 0 without the lock (the holder encodes them)."""
        self.attach(service)
        if not self.held:
            return 0
        service.collection.hold_writer_role(True)
        worker = self._worker(service)
        left = 0
        while done := worker.run_once():
            left += done
        return left

    # -- the end of the role --------------------------------------------------------------------------------
    def stop(self, final: bool = True) -> None:
        """Give the role up in order: the failover thread (it may be starting the worker right now), the
        worker and the janitor, the final snapshot (``final``: a clean stop leaves nothing to replay at the
        next start), the checkpoint (the rows written here go into the main file), then the lock."""
        self._stopping.set()
        if self._watch is not None:
            self._watch.join(timeout=60)
        try:
            if self.worker is not None:
                self.worker.stop()
            if self.janitor is not None:
                self.janitor.stop()
            if self.snapshots is not None:
                self.snapshots.stop(final=final)  # the final snapshot, then a TRUNCATE checkpoint
            elif final and self.held and self.collection is not None:
                self.collection.write_snapshot()
        finally:
            try:
                if self.snapshots is None and self.collection is not None:
                    self.collection.store.checkpoint()  # after a bulk load its rows go into the main file
            finally:
                self.lock.release()


def write_snapshot_if_free(backend: StorageBackend, open_collection: Callable[[], Collection]) -> bool:
    """Write one snapshot from ``open_collection()`` when no server or worker holds the role (nothing writes
    snapshots here then); False, and nothing opened, when one does."""
    writer = Writer(backend)
    if not writer.acquire():
        return False
    try:
        writer.collection = open_collection()
    finally:
        writer.stop()
    return True


def run_worker(
    data_dir: Path,
    models_dir: Path,
    config: str,
    batch: int,
    on_ready: Callable[[GeolocService], None],
    retry_seconds: float | None = None,
    max_attempts: int = 3,
    sizing: IndexSizing | None = None,
    backend: StorageBackend | None = None,
) -> None:
    """``geoloc worker``: take the lock (``WriterBusy`` when another process holds it; nothing is opened),
    open the service, call ``on_ready`` and run the role in this (the main) thread until SIGTERM or Ctrl-C;
    a clean stop writes the last snapshot. ``retry_seconds``: on PostgreSQL, how often the lock's session
    is checked (and, once lost, the lock retried): see ``Writer.run``. ``sizing``: the process's
    ``Settings.index_sizing``, so the worker switches index kinds at the same size as the server;
    ``backend``: the process's (``Settings.backend``; None: SQLite in ``data_dir``)."""
    import signal

    backend = backend or SqliteBackend(data_dir)
    writer = Writer(backend, batch, max_attempts=max_attempts)
    if not writer.acquire():
        raise WriterBusy(f"another worker already holds {writer.lock.where}")
    service = GeolocService.open(data_dir, models_dir, config, sizing=sizing, backend=backend)
    signal.signal(signal.SIGTERM, lambda *_: writer.request_stop())
    on_ready(service)
    writer.run(service, retry_seconds)
