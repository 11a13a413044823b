"""Image files nothing owns: orphans (no row names them), stale temporary files, queued removals.

How they arise: a process killed between writing an upload's images and committing its rows, an insert
that failed on a full disk after its files were written, a delete whose file could not be removed (its
removal stays queued). None of them is ever read, but they hold disk and, for photos, their EXIF GPS.

Why an age threshold: an upload writes its files *before* the transaction that commits its rows, so a
young file no row names may be an upload in flight. Only files older than ``MIN_AGE_S`` are removed, and
each unlink happens under the database's write lock after re-checking that no row names the file (an add
of the same bytes re-checks its file under that lock too: see ``app.storage.removals``).

Cost: a sweep reads every file name of ``images/`` (a chunk at a time: its memory does not grow with the
collection), stats the unnamed ones and looks each name up in the sha256 index, so its time is
O(collection); the writer process runs it in a background thread once an hour
(``Janitor``), never on a request, and its unlinks take the write lock for one short transaction per
``CHUNK`` names. Retrying queued removals reads a table that is nearly always empty,
so it runs every few seconds.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

from app.storage.errors import is_storage_error
from app.storage.store import ReferenceStore

log = logging.getLogger("geoloc.orphans")

#: Files younger than this are never swept: an upload may have written them and not committed its rows yet.
MIN_AGE_S = 3600.0
#: Names looked up (and unlinked under the write lock) per transaction: short lock holds.
CHUNK = 500


@dataclass
class SweepReport:
    removed: list[str] = field(default_factory=list)  # orphan image files removed
    removed_tmp: list[str] = field(default_factory=list)  # stale temporary files removed
    young: list[str] = field(default_factory=list)  # unnamed files kept: younger than the threshold
    failed: list[str] = field(default_factory=list)  # could not be removed (retried at the next sweep)

    def lines(self, min_age_s: float) -> list[str]:
        out = [
            f"removed {len(self.removed)} image files no row names, older than {min_age_s:.0f} s",
            f"removed {len(self.removed_tmp)} stale temporary files",
        ]
        if self.young:
            out.append(
                f"kept {len(self.young)} unnamed files younger than {min_age_s:.0f} s (uploads may be writing "
                "them): run again later, or with --min-age 0 once no process uses the data dir"
            )
        if self.failed:
            out.append(f"could not remove {len(self.failed)} files: {', '.join(self.failed[:10])}")
        return out


def _chunks(names: Iterator[os.DirEntry], n: int) -> Iterator[list[os.DirEntry]]:
    chunk: list[os.DirEntry] = []
    for e in names:
        chunk.append(e)
        if len(chunk) == n:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _age(entry: os.DirEntry, now: float) -> float:
    try:
        return now - entry.stat(follow_symlinks=False).st_mtime
    except FileNotFoundError:
        return -1.0  # gone meanwhile: nothing to do


def sweep(store: ReferenceStore, min_age_s: float = MIN_AGE_S) -> SweepReport:
    """Remove image files no row names and temporary files (``.NAME.PID.TID.tmp``, left by a killed
    writer), both older than ``min_age_s``. O(collection) in time, one ``CHUNK`` of entries in memory: the
    folder is read as it is swept, never listed whole (a list of every entry held hundreds of bytes per
    reference while the sweep ran). See the module's docstring."""
    r = SweepReport()
    now = time.time()
    with os.scandir(store.images_dir) as it:
        for chunk in _chunks((e for e in it if e.is_file(follow_symlinks=False)), CHUNK):
            images = []
            for e in chunk:
                if not e.name.startswith("."):
                    images.append(e)
                elif e.name.endswith(".tmp"):
                    _remove_stale_tmp(e, now, min_age_s, r)
            if images:
                _sweep_images(store, images, now, min_age_s, r)
    return r


def _remove_stale_tmp(e: os.DirEntry, now: float, min_age_s: float, r: SweepReport) -> None:
    if _age(e, now) <= min_age_s:
        return
    try:
        os.unlink(e.path)
        r.removed_tmp.append(e.name)
    except FileNotFoundError:
        pass
    except OSError as err:
        log.warning("cannot remove %s: %s", e.path, err)
        r.failed.append(e.name)


def _sweep_images(store: ReferenceStore, chunk: list[os.DirEntry], now: float, min_age_s: float, r: SweepReport):
    """One chunk of image files: the names no row names looked up at once, the old ones removed under the
    write lock (re-checked there), the young ones reported."""
    named = store.named_files([e.name for e in chunk])
    old = []
    for e in chunk:
        if e.name in named:
            continue
        age = _age(e, now)
        if age > min_age_s:
            old.append(e.name)
        elif age >= 0:
            r.young.append(e.name)
    if old:
        removed, failed = store.remove_unnamed(old)  # re-checked under the write lock
        r.removed += removed
        r.failed += failed


def retry_removals(store: ReferenceStore) -> tuple[list[str], list[str]]:
    """Remove every queued file that still can be (in chunks); returns (removed, still failing)."""
    removed: list[str] = []
    failed: list[str] = []
    queued = store.queued_removals()
    for n in range(0, len(queued), CHUNK):
        done, bad = store.remove_queued(queued[n : n + CHUNK])
        removed += done
        failed += bad
    return removed, failed


class Janitor:
    """The writer process's housekeeping thread (the process holding the worker lock runs it, so one per
    data dir): queued removals retried every ``retry_s``, an orphan sweep at start and every ``sweep_s``."""

    def __init__(
        self,
        store: ReferenceStore,
        retry_s: float = 5.0,
        sweep_s: float = 3600.0,
        min_age_s: float = MIN_AGE_S,
    ):
        self.store = store
        self.retry_s, self.sweep_s, self.min_age_s = retry_s, sweep_s, min_age_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def run_once(self, now: float, next_sweep: float) -> float:
        """One round; returns when the next sweep is due."""
        try:
            if self.store.queued_removals():
                removed, failed = retry_removals(self.store)
                if removed:
                    log.info("removed %d queued image files (%d still failing)", len(removed), len(failed))
            if now >= next_sweep:
                next_sweep = now + self.sweep_s
                r = sweep(self.store, self.min_age_s)
                if r.removed or r.removed_tmp or r.failed:
                    log.info("orphan sweep: %s", "; ".join(r.lines(self.min_age_s)))
        except Exception as e:  # housekeeping must never stop the writer; the next round tries again
            if is_storage_error(e):
                log.warning("housekeeping paused: %s", e)
            else:
                log.exception("housekeeping failed")
        return next_sweep

    def run(self) -> None:
        next_sweep = time.time()
        while not self._stop.is_set():
            next_sweep = self.run_once(time.time(), next_sweep)
            self._stop.wait(self.retry_s)

    def start(self) -> Janitor:
        self._thread = threading.Thread(target=self.run, name="geoloc-janitor", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 30.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
