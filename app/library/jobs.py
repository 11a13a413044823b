"""A library scan as a batch job of the server (POST /library/scans): one thread per scan, one scan per
library at a time, its state and results in the journal (so GET answers from any thread, and a restart
loses only the run in flight, which the next POST resumes).

Why a folder root: the server reads folders of its own file system on a client's word, so it reads only
folders under ``GEOLOC_LIBRARY_ROOT`` (unset: the API scans nothing; the CLI has no such limit), and never
a manifest (its rows may name any file, ``../`` or absolute). Every file it then reads (thumbnails) or
writes (write-back, undo) is checked again, resolved, against the root: a journal row names a path, and
the path may have become a link since.

Why a lock per scan: a scan, a write and an undo of the same library must not interleave (a write during
a scan would race its journal rows; two undos would restore twice). The server's scans use one thread by
default: they share the cores with /locate, which must stay responsive."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from app.engine.errors import GeolocError
from app.engine.imageio import ImageLimits
from app.ingestion.thumbnails import render_thumbnail
from app.library.exports import render
from app.library.review import decide
from app.library.scan import ScanOptions, scan_library
from app.library.writeback import undo, write_back
from app.storage.library import LOCATED, PROBLEM, JournalError, LibraryJournal, PhotoRecord
from app.usecases.service import GeolocService
from app.user_files import FileTooLarge, is_within, read_regular

log = logging.getLogger("geoloc.library")
#: How long ``close`` waits for a scan thread to stop after the stop flag (it stops between two photos).
STOP_WAIT_S = 30.0


class FolderRefused(ValueError):
    """The folder is outside the library root, or no root is set, or it is not a folder."""


class ScanBusy(RuntimeError):
    """A scan, write or undo of this library is in progress."""


class LibraryUnavailable(RuntimeError):
    """The data dir's library journal cannot be used (another layout, damaged, not SQLite)."""


class LibraryJobs:
    """The server's library scans over one data dir. Made once per process (``open``), ``close``d at its
    shutdown: the stop flag ends the scan threads between two photos."""

    @classmethod
    def open(cls, data_dir: Path, root: Path | None) -> LibraryJobs:
        """``LibraryJobs(data_dir, root)``; a journal that cannot be used raises ``LibraryUnavailable``, which
        a caller says in a line (the journal's own error is the storage's)."""
        try:
            return cls(data_dir, root)
        except JournalError as e:
            raise LibraryUnavailable(str(e)) from None

    def __init__(self, data_dir: Path, root: Path | None):
        self.journal = LibraryJournal(data_dir)
        self.data_dir = Path(data_dir).resolve()
        self.root = root.resolve() if root is not None else None
        self._threads: dict[str, threading.Thread] = {}
        self._locks: dict[str, threading.Lock] = {}
        self._lock = threading.Lock()
        self.stop = threading.Event()
        # No scan runs in this process yet: one the journal says is running died with an earlier process.
        for sid in self.journal.interrupt_running():
            log.warning("library scan %s was left running by an earlier process: marked interrupted", sid)

    def folder(self, text: str) -> Path:
        """``text`` as a folder under the root (symlinks resolved first: a link cannot lead out of it)."""
        if self.root is None:
            raise FolderRefused("this server scans no folders: set GEOLOC_LIBRARY_ROOT to the folder it may read")
        if "\x00" in text:
            raise FolderRefused("the folder name contains a NUL character")
        path = Path(text)
        try:
            path = (path if path.is_absolute() else self.root / path).resolve()
            if not is_within(path, self.root):
                raise FolderRefused(f"the folder must lie under the library root {self.root}")
            if not path.exists():
                raise FolderRefused(f"{path} does not exist")
            if not path.is_dir():  # a manifest's rows may name files anywhere: the API takes folders only
                raise FolderRefused(f"{path} is not a folder (the API scans folders only; manifests: the CLI)")
        except OSError as e:  # a name too long, a loop of links, a folder that cannot be read
            raise FolderRefused(f"the folder cannot be used: {e.strerror or e}") from None
        if is_within(path, self.data_dir):
            raise FolderRefused("the folder lies inside the server's data dir: its files are the service's own")
        return path

    def _scan_lock(self, sid: str) -> threading.Lock:
        with self._lock:
            return self._locks.setdefault(sid, threading.Lock())

    @contextmanager
    def exclusive(self, sid: str) -> Iterator[None]:
        """Hold the library's lock for a write or an undo; ``ScanBusy`` at once if a scan (or another write)
        holds it (an API thread never waits minutes for a scan)."""
        lock = self._scan_lock(sid)
        if not lock.acquire(blocking=False):
            raise ScanBusy("this library is being scanned or written: try again once that is done")
        try:
            yield
        finally:
            lock.release()

    def start(self, service: GeolocService, folder: Path, options: ScanOptions) -> str:
        """Start scanning ``folder`` (a scan already running for it is left to run); returns its id."""
        with self._lock:
            if self.stop.is_set():
                raise ScanBusy("the server is shutting down")
            sid = self.journal.scan_of(folder)
            running = self._threads.get(sid) if sid else None
            if sid is not None and running is not None and running.is_alive():
                return sid
            sid = self.journal.start_scan(folder, 0)
            t = threading.Thread(
                target=self._run, args=(service, folder, options, sid), name=f"library-{sid}", daemon=True
            )
            self._threads[sid] = t
            t.start()
        return sid

    def _run(self, service: GeolocService, folder: Path, options: ScanOptions, sid: str) -> None:
        with self._scan_lock(sid):
            try:
                scan_library(service, folder, options, self.journal, stop=self.stop)
            except Exception as e:  # the server goes on; the scan's row says why it stopped
                log.warning("library scan of %s failed: %s", folder, e)
                self.journal.finish_scan(sid, "failed", str(e) or type(e).__name__)

    def wait(self, sid: str, timeout: float | None = None) -> None:
        t = self._threads.get(sid)
        if t is not None:
            t.join(timeout)

    def close(self) -> None:
        """Stop the scans (between two photos) and close the journal."""
        self.stop.set()
        for t in list(self._threads.values()):
            t.join(STOP_WAIT_S)
        self.journal.close()

    # -- a scan's journal, as the API reads and changes it ------------------------------------------------
    def scan(self, sid: str) -> dict | None:
        """The scan's state; None when there is no such scan."""
        return self.journal.scan(sid)

    def results(self, sid: str) -> list[PhotoRecord]:
        """The scan's photos that were located or could not be (its references are the collection's)."""
        return [r for r in self.journal.photos(sid) if r.kind in (LOCATED, PROBLEM)]

    def photo(self, sid: str, photo_id: int) -> PhotoRecord | None:
        return self.journal.photo(sid, photo_id)

    def photo_thumbnail(self, sid: str, photo_id: int, px: int, limits: ImageLimits) -> bytes | None:
        """``thumbnail`` of the journalled photo; None when the scan has no such photo."""
        rec = self.journal.photo(sid, photo_id)
        return None if rec is None else self.thumbnail(Path(rec.path), px, limits)

    def decide(self, sid: str, photo_id: int, action: str, lat: float | None, lon: float | None) -> PhotoRecord:
        """``app.library.review.decide`` on this library's journal."""
        return decide(self.journal, sid, photo_id, action, lat, lon)

    def write_back(self, sid: str, in_file: bool, dry_run: bool) -> dict:
        """``app.library.writeback.write_back`` under the root, holding the library's lock (``exclusive``)."""
        with self.exclusive(sid):
            return write_back(self.journal, sid, self.data_dir, in_file, dry_run, self.root)

    def undo(self, sid: str) -> dict:
        """``app.library.writeback.undo`` under the root, holding the library's lock (``exclusive``)."""
        with self.exclusive(sid):
            return undo(self.journal, sid, self.root)

    def export(self, sid: str, fmt: str, every: bool) -> str:
        """The scan's accepted positions (every suggestion with ``every``) as ``fmt`` (``app.library.exports``)."""
        return render(self.journal.photos(sid), fmt, every)

    def thumbnail(self, path: Path, px: int, limits: ImageLimits) -> bytes:
        """A JPEG of a journalled photo's pixels only (no EXIF, XMP or comment), upright, at most ``px`` on a
        side, decoded as a reference's thumbnail is (``app.ingestion.thumbnails``: reduced, under the pixel
        budget). Read only from a regular file under the root, never through a link (one put there since
        the scan is refused), and no larger than the server's upload limit."""
        try:
            data = read_regular(path, self.root or path.parent.resolve(), limits.max_bytes)
        except FileTooLarge:
            raise GeolocError(f"{path.name} is larger than the server's image limit") from None
        except OSError as e:
            raise FileNotFoundError(f"{path.name} is no longer a file of the library: {e.strerror or e}") from None
        return render_thumbnail(data, px, limits.stored())
