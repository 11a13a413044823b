"""The library run: `geoloc library scan DIR`, POST /library/scans and the page call
``scan_library``.

0. The library is a folder (its photos with EXIF GPS are the references) or a manifest (its ``db`` rows
   are, at their stated positions; its ``query`` rows are located).
1. Every photo's header is read (``app.library.photos``, threads): GPS, capture time, camera.
2. The photos with GPS go into the data dir through the ingest path (`geoloc ingest`'s run, its journal,
   claims and report), so the collection is the library itself; an existing data dir is used as it is.
   Photos this library located and wrote GPS into are never taken as references.
3. The photos without GPS are located (``GeolocService.locate``, /locate's answer) on ``workers`` threads,
   fused with the time prior (``app.library.suggest``) and journalled one by one: a second run, or a run
   after a crash, skips what is done (same path, size and mtime).
4. With the time prior on, each camera's run of photos close in time is read as one walk
   (``app.library.joint``): a photo not confident alone that the run places gets the run's position (also
   when nothing was new to locate: a scan stopped before this step ends it).

A file that cannot be read is journalled as a problem with its reason and the run goes on.

Why a bounded window of work: the thread pool gets at most ``WINDOW_PER_WORKER`` photos per thread ahead
of the one being journalled, never the whole library up front; so a stop (the server shutting down, the
user's Ctrl-C) waits for a handful of photos, not for the rest of a 10^5-photo scan."""

from __future__ import annotations

import csv
import logging
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TypeVar

from app.domain import LocateOptions
from app.engine.errors import GeolocError
from app.engine.progress import Progress
from app.ingestion.bulk import IngestOptions, ingest
from app.ingestion.sources import Source, SourceItem
from app.library.joint import joint_suggestions
from app.library.photos import PhotoMeta, read_meta, same_stat, walk_photos
from app.library.suggest import suggestion
from app.library.timeprior import Anchor, time_prior
from app.manifests import ManifestError, read_manifest
from app.settings import usable_cpus
from app.storage.library import LOCATED, PROBLEM, LibraryJournal
from app.usecases.sequence import SEQUENCE
from app.usecases.service import GeolocService
from app.user_files import is_within, read_regular

log = logging.getLogger("geoloc.library")
T, R = TypeVar("T"), TypeVar("R")
#: Photos in flight per thread (read or being located) ahead of the one journalled next.
WINDOW_PER_WORKER = 2


class LibraryError(ValueError):
    """The library as a whole cannot be scanned (no such folder, nothing to locate against). ``problems``:
    the files found unusable before it stopped, (file, reason), so that they are reported all the same."""

    def __init__(self, message: str, problems: list[tuple[str, str]] | None = None):
        super().__init__(message)
        self.problems = problems or []


@dataclass(frozen=True)
class ScanOptions:
    workers: int = field(default_factory=usable_cpus)  # threads reading and locating (one per usable CPU)
    time_prior: bool = True
    runs: bool = True  # with the time prior: each camera's runs read as walks (step 4; a bench compares without)
    rerank: bool = False
    ray: str | None = None  # the ingest step's engine (`geoloc ingest --ray`)


@dataclass
class ScanSummary:
    scan_id: str
    photos: int = 0
    references: int = 0  # photos with GPS (in the collection)
    added: int = 0  # of which new in the data dir
    located: int = 0  # photos without GPS located by this run
    unchanged: int = 0  # located by an earlier run, not read again
    placed: int = 0
    confident: int = 0
    by_sequence: int = 0  # of those located now, placed by the run of photos around them (``app.library.joint``)
    problems: list[tuple[str, str]] = field(default_factory=list)  # (file, reason)
    workers: int = 1


@dataclass(frozen=True)
class PathsSource(Source):
    """The ingest step's source: exactly the library's geotagged photos (a folder source would also read
    the photos to locate and report each one as "no GPS")."""

    paths: tuple[Path, ...] = ()
    positions: dict | None = None  # a manifest's: path -> (lat, lon); None: each photo's EXIF GPS

    def items(self):
        where = self.positions or {}
        return (SourceItem(p, *where.get(p, (None, None))) for p in self.paths)

    def count(self) -> int:
        return len(self.paths)


def scan_library(
    service: GeolocService,
    folder: Path,
    options: ScanOptions,
    journal: LibraryJournal,
    say: Callable[[str], None] = log.info,
    progress: Callable[[int, str], Progress] | None = None,
    stop: threading.Event | None = None,
    files: tuple[list[Path], dict[Path, tuple[float, float]] | None] | None = None,
) -> ScanSummary:
    """See the module docstring. ``progress(total, desc)`` makes the bar (default: ``Progress``); ``stop``
    set ends the run between two photos (state "interrupted"); ``files``: ``library_files(folder)`` when
    the caller already checked the folder."""
    folder = Path(folder).resolve()
    data_dir = Path(service.data_dir).resolve()
    paths, positions = files if files is not None else library_files(folder, data_dir)
    # A folder's files are read only where they are regular files inside it (never through a link): the
    # folder may change between the listing and the reads. A manifest's rows may name files anywhere.
    within = folder if positions is None else None
    workers = max(1, options.workers)
    make_bar = progress or (lambda total, desc: Progress(total, desc=desc))
    sid = journal.start_scan(folder, len(paths))
    summary = ScanSummary(sid, photos=len(paths), workers=workers)
    # An interrupted run (Ctrl-C, a failure) cancels the photos not started yet instead of locating the
    # rest of a large library on its way out: what is done is journalled, the next run does the rest.
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        read = lambda p: read_meta(p, within)  # noqa: E731
        metas = list(bounded_map(pool, read, paths, workers * WINDOW_PER_WORKER, stop))
        if stop is not None and stop.is_set():
            journal.finish_scan(sid, "interrupted", "stopped (the server shut down): scan again to resume")
            return summary
        if positions is not None:  # a manifest says which photos are references, and where
            metas = [replace(m, gps=positions.get(m.path)) for m in metas]
        refs, todo = _sort_out(metas, journal, sid, summary)
        if refs:
            summary.added = _ingest(service, folder, within, refs, positions, workers, options.ray, say)
        anchors = [Anchor(m.gps[0], m.gps[1], m.taken, m.camera) for m in refs if m.taken and m.gps]
        located_now: set[str] = set()
        if not todo:  # nothing new to locate: the runs are read all the same (a scan stopped before them)
            _locate_jointly(service, journal, sid, anchors, options, summary, located_now)
            journal.finish_scan(sid, "done", None)
            return summary
        if service.size == 0:
            raise LibraryError(
                f"{folder} has no photo with GPS and the data dir holds no references: nothing to locate "
                "the other photos against (add geotagged photos, or give a --data-dir with a collection)",
                summary.problems,
            )
        bar = make_bar(len(todo), f"locate ({workers} threads)")
        try:
            locate = lambda m: _locate(service, m, anchors, options, within)  # noqa: E731
            for n, (meta, result) in enumerate(
                bounded_map(pool, locate, todo, workers * WINDOW_PER_WORKER, stop), start=1
            ):
                kind = PROBLEM if "problem" in result else LOCATED
                journal.record(sid, meta.path, meta.size, meta.mtime_ns, kind, result)
                if kind == PROBLEM:
                    summary.problems.append((str(meta.path), result["reason"]))
                else:
                    located_now.add(str(meta.path))
                    summary.located += 1
                    summary.placed += bool(result["placed"])
                    summary.confident += bool(result["confident"])
                bar.update(1)
                journal.progress(sid, n)
        finally:
            bar.close()
        if stop is not None and stop.is_set():
            journal.finish_scan(sid, "interrupted", "stopped (the server shut down): scan again to resume")
            return summary
        _locate_jointly(service, journal, sid, anchors, options, summary, located_now)
    except BaseException as e:
        journal.finish_scan(sid, "failed", str(e) or type(e).__name__)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    journal.finish_scan(sid, "done", None)
    return summary


def _locate_jointly(
    service: GeolocService,
    journal: LibraryJournal,
    sid: str,
    anchors: list[Anchor],
    options: ScanOptions,
    summary: ScanSummary,
    located_now: set[str],
) -> None:
    """Step 4: the runs of the scan's located photos (this run's and earlier runs') read as walks, or, with
    the runs off, earlier runs' placements taken back. A suggestion they change is journalled again, unless
    the photo was reviewed already (a decision is never cleared by a neighbour); this run's counts of placed
    and confident photos made final."""
    calibration = service.answer_calibration(LocateOptions(top_k=10, rerank=options.rerank))
    records = [r for r in journal.photos(sid, LOCATED) if r.decision is None]
    enabled = options.time_prior and options.runs
    changed = joint_suggestions([r.result for r in records], anchors, calibration, enabled=enabled)
    for r in records:
        new = changed.get(r.result["file"])
        if new is None:
            continue
        journal.record(sid, Path(r.path), r.size, r.mtime_ns, LOCATED, new)
        if r.path in located_now:
            summary.placed += int(new["placed"]) - int(r.result["placed"])
            summary.confident += int(new["confident"]) - int(r.result["confident"])
    summary.by_sequence = sum(
        (changed.get(r.result["file"]) or r.result).get("basis") == SEQUENCE for r in records if r.path in located_now
    )


def bounded_map(
    pool: ThreadPoolExecutor, fn: Callable[[T], R], items: Iterable[T], window: int, stop: threading.Event | None
) -> Iterator[R]:
    """``pool.map(fn, items)`` in order, with at most ``window`` calls submitted ahead, and none submitted
    once ``stop`` is set (the ones in flight finish and are yielded)."""
    pending: deque = deque()
    it = iter(items)

    def fill() -> None:
        while len(pending) < max(1, window) and not (stop is not None and stop.is_set()):
            try:
                item = next(it)
            except StopIteration:
                return
            pending.append(pool.submit(fn, item))

    fill()
    while pending:
        yield pending.popleft().result()
        fill()


def _sort_out(
    metas: list[PhotoMeta], journal: LibraryJournal, sid: str, summary: ScanSummary
) -> tuple[list[PhotoMeta], list[PhotoMeta]]:
    """(the references, the photos to locate now); problem files journalled and counted, photos located by
    an earlier run and unchanged since counted. A photo that any library of this journal located stays one
    to review even once GPS was written into it: never a reference (elsewhere, the mark written beside the
    position says the same: ``app.engine.imageio.ESTIMATE_MARK``)."""
    known = journal.known(sid)
    ours = journal.located_paths()
    refs = [m for m in metas if m.gps is not None and m.problem is None and str(m.path) not in ours]
    todo: list[PhotoMeta] = []
    for m in metas:
        if m.problem is not None:
            summary.problems.append((str(m.path), m.problem))
            journal.record(sid, m.path, m.size, m.mtime_ns, PROBLEM, {"file": str(m.path), "reason": m.problem})
        elif m.gps is None or str(m.path) in ours:
            rec = known.get(str(m.path))
            if rec is not None and rec.kind == LOCATED and same_stat(m, rec.size, rec.mtime_ns):
                summary.unchanged += 1
            else:
                todo.append(m)
    summary.references = len(refs)
    return refs, todo


def library_files(
    path: Path, data_dir: Path | None = None
) -> tuple[list[Path], dict[Path, tuple[float, float]] | None]:
    """The library's photos, and where a manifest puts its references (None for a folder: EXIF GPS).

    A folder: every photo under it; those with EXIF GPS are the references. A manifest (a CSV with
    ``image,lat,lon,split``): its ``db`` rows are the references at the manifest's positions, its ``query``
    rows are the photos to locate (whatever GPS their EXIF holds), ``train`` rows are left out.

    ``data_dir`` (resolved) is never part of a library: a folder inside it is refused, and a folder that
    holds it is scanned without it (its stored images and undo backups would become photos to write)."""
    if data_dir is not None and is_within(path.resolve(), data_dir):
        raise LibraryError(f"{path} lies inside the data dir {data_dir}: the service's own files are no library")
    if path.is_dir():
        paths = walk_photos(path, data_dir)
        if not paths:
            raise LibraryError(f"{path} holds no photos (.jpg .jpeg .png .webp .tif .tiff .heic ...)")
        return paths, None
    if not path.is_file():
        raise LibraryError(f"{path} is neither a folder nor a manifest")
    try:
        rows = read_manifest(path)
    except (ManifestError, UnicodeDecodeError, csv.Error) as e:
        raise LibraryError(f"{path} is not a manifest (image,lat,lon,split): {e}") from None
    positions = {r.image: (r.lat, r.lon) for r in rows if r.split == "db"}
    if data_dir is not None:
        positions = {p: v for p, v in positions.items() if not is_within(p.resolve(), data_dir)}
        rows = [r for r in rows if not is_within(r.image.resolve(), data_dir)]
    queries = [r.image for r in rows if r.split == "query" and r.image not in positions]
    if not queries:
        raise LibraryError(f"{path} has no query rows: nothing to locate")
    return sorted(set(positions) | set(queries)), positions


def _ingest(
    service: GeolocService, folder: Path, within: Path | None, refs: list[PhotoMeta], positions, workers: int, ray, say
) -> int:
    kind = "folder" if positions is None else "manifest"
    source = PathsSource(kind, folder, within=within, paths=tuple(m.path for m in refs), positions=positions)
    summary, _ = ingest(service, source, IngestOptions(workers=workers, ray=ray), say=say)
    say(
        f"collection: {summary.added} new references from {len(refs)} photos with GPS "
        f"({summary.present} already present); index size {service.size}"
    )
    return summary.added


def _locate(service: GeolocService, meta: PhotoMeta, anchors: list[Anchor], options: ScanOptions, within: Path | None):
    """One photo's suggestion, or ``{"problem": ...}`` when it cannot be located (never raises)."""
    try:
        data = read_regular(meta.path, within, service.limits.max_bytes)
        answer = service.locate(data, LocateOptions(top_k=10, rerank=options.rerank))
    except (OSError, GeolocError) as e:
        reason = f"cannot read the file: {e.strerror or e}" if isinstance(e, OSError) else str(e)
        return meta, {"file": str(meta.path), "problem": True, "reason": reason}
    prior = time_prior(meta.taken, meta.camera, anchors) if options.time_prior else None
    return meta, suggestion(meta, answer, prior)
