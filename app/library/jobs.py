"""A library scan as a batch job of the server (POST /library/scans): one thread per scan, one scan per
library at a time, its state and results in the journal (so GET answers from any thread, and a restart
loses only the run in flight, which the next POST resumes).

Why a folder root: the server reads folders of its own file system on a client's word, so it reads only
under ``GEOLOC_LIBRARY_ROOT`` (unset: the API scans nothing; the CLI has no such limit)."""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from app.engine.imageio import ImageLimits
from app.library.scan import ScanOptions, scan_library
from app.service import GeolocService
from app.storage.library import LibraryJournal, scan_id
from app.thumbnails import render_thumbnail

log = logging.getLogger("geoloc.library")


class FolderRefused(ValueError):
    """The folder is outside the library root, or no root is set, or it is not a folder."""


class LibraryJobs:
    """The server's library scans over one data dir."""

    def __init__(self, data_dir: Path, root: Path | None):
        self.journal = LibraryJournal(data_dir)
        self.root = root.resolve() if root is not None else None
        self._threads: dict[str, threading.Thread] = {}
        self._lock = threading.Lock()

    def folder(self, text: str) -> Path:
        """``text`` as a folder under the root (symlinks resolved first: a link cannot lead out of it)."""
        if self.root is None:
            raise FolderRefused("this server scans no folders: set GEOLOC_LIBRARY_ROOT to the folder it may read")
        path = Path(text)
        path = (path if path.is_absolute() else self.root / path).resolve()
        if path != self.root and self.root not in path.parents:
            raise FolderRefused(f"the folder must lie under the library root {self.root}")
        if not path.exists():
            raise FolderRefused(f"{path} does not exist")
        return path

    def start(self, service: GeolocService, folder: Path, options: ScanOptions) -> str:
        """Start scanning ``folder`` (a scan already running for it is left to run); returns its id."""
        sid = scan_id(folder)
        with self._lock:
            running = self._threads.get(sid)
            if running is not None and running.is_alive():
                return sid
            self.journal.start_scan(folder, 0)
            t = threading.Thread(target=self._run, args=(service, folder, options), name=f"library-{sid}", daemon=True)
            self._threads[sid] = t
            t.start()
        return sid

    def _run(self, service: GeolocService, folder: Path, options: ScanOptions) -> None:
        try:
            scan_library(service, folder, options, self.journal)
        except Exception as e:  # recorded in the journal by scan_library; the server goes on
            log.warning("library scan of %s failed: %s", folder, e)

    def wait(self, sid: str, timeout: float | None = None) -> None:
        t = self._threads.get(sid)
        if t is not None:
            t.join(timeout)

    def close(self) -> None:
        self.journal.close()


def thumbnail(path: Path, px: int) -> bytes:
    """A JPEG of the photo's pixels only (no EXIF, XMP or comment), upright, at most ``px`` on a side:
    decoded as a reference's thumbnail is (``app.thumbnails``: reduced, under the process's pixel budget;
    a 7000 x 7000 WebP decoded whole per request cost gigabytes, issue 30)."""
    return render_thumbnail(path.read_bytes(), px, ImageLimits().stored())
