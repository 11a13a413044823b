"""One `geoloc ingest` run: read a source in chunks, accept each chunk through the core (pending rows, one
transaction), claim the new rows, encode them with an engine and complete them in batches.

Why this shape:
- Streaming chunks (``chunk`` files at a time) keeps memory flat on 10^6 photos: a chunk is read,
  validated with ``app.ingestion.uploads.prepare_upload`` (the API's limits), accepted, journalled, and
  handed on; the engine pulls the next items only as it needs them, so the next chunk is read while this
  one encodes.
- Accepted rows are the core's ``pending`` rows, so a crash loses nothing; the run claims them for a lease
  so that a running server's worker (which reads ``store.pending``) does not encode the same rows, and a
  crashed run's claims simply expire and the server's worker takes the rows over.
- The journal (``app.storage.journal``) lets a re-run skip unchanged files on a ``stat``; content hashes still
  find duplicates among the files it does read.
- Skipped files go to a CSV report (path, reason) written as the run goes, never held in memory.
"""

from __future__ import annotations

import csv
import os
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from app.domain import Upload
from app.engine.errors import (
    GeolocError,
    ImageTooLarge,
    ImageTooSmall,
    NoGpsInImage,
    UnreadableImage,
    UnsupportedImageFormat,
)
from app.engine.progress import Progress
from app.ingestion.encoding.items import Encoded, EncodeItem
from app.ingestion.encoding.local import batched, encode_and_complete, make_engine
from app.ingestion.sources import Source, SourceItem
from app.ingestion.uploads import prepare_upload
from app.ingestion.writer import Writer
from app.storage.journal import FileKey, Journal
from app.storage.store import NewReference
from app.usecases.service import GeolocService
from app.user_files import FileTooLarge, NotARegularFile, read_regular

#: How long this run's claim on a row lasts: the row is encoded within seconds of being claimed, so a
#: claim that outlives this belongs to a run that died, and a worker may take the row over.
CLAIM_LEASE_S = 900.0
HEIC_UNSUPPORTED = "HEIC unsupported: pip install pillow-heif"


@dataclass(frozen=True)
class IngestOptions:
    chunk: int = 128  # files read, validated and accepted per transaction
    batch: int = 32  # encoded rows completed per transaction
    workers: int = 1  # threads reading and validating, and encoding threads (local engine) or Ray actors
    ray: str | None = None
    shared_fs: bool = False
    lease_s: float = CLAIM_LEASE_S


@dataclass
class Summary:
    added: int = 0  # new references stored by this run
    duplicates: int = 0  # files whose bytes were already stored
    unchanged: int = 0  # files the journal knew (same path, size, mtime): not read again
    failed: int = 0  # accepted but the encoder could not use them
    skipped: Counter = field(default_factory=Counter)  # reason category -> files
    report: Path | None = None

    @property
    def present(self) -> int:
        return self.duplicates + self.unchanged


class SkipReport:
    """The CSV of files not ingested (path, reason), created at the first one and appended as the run goes."""

    def __init__(self, folder: Path):
        self.path = folder / f"ingest-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{os.getpid()}.csv"
        self._file = None
        self._writer = None

    def add(self, path: Path | str, reason: str) -> None:
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = self.path.open("w", newline="")
            self._writer = csv.writer(self._file)
            self._writer.writerow(["path", "reason"])
        self._writer.writerow([str(path), reason])

    @property
    def written(self) -> bool:
        return self._writer is not None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()


def skip_reason(exc: BaseException) -> tuple[str, str]:
    """(category for the summary, full reason for the report) of a file that could not be accepted."""
    text = str(exc)
    if isinstance(exc, NoGpsInImage) and "estimated" in text:
        return "estimated GPS", "its EXIF GPS is this service's estimate, not a measured position"
    if isinstance(exc, NoGpsInImage):
        return "no GPS in EXIF", "no position given and no GPS position in its EXIF"
    if isinstance(exc, UnsupportedImageFormat) and ("HEIC" in text or "AVIF" in text):
        return "HEIC unsupported", HEIC_UNSUPPORTED
    if isinstance(exc, UnsupportedImageFormat):
        return "unsupported format", text
    if isinstance(exc, ImageTooLarge | FileTooLarge):
        return "too large", text
    if isinstance(exc, ImageTooSmall):
        return "too small", text
    if isinstance(exc, UnreadableImage):
        return ("not an image" if "are not a" in text or "empty" in text else "damaged or truncated"), text
    if isinstance(exc, NotARegularFile):
        return "not a regular file", f"not read: {exc.strerror or exc}"
    if isinstance(exc, OSError):
        return "cannot read the file", f"cannot read the file: {exc.strerror or exc}"
    return "bad metadata", text


class IngestRun:
    """Streams one source into the data dir of ``service``; see the module docstring."""

    def __init__(self, service: GeolocService, source: Source, options: IngestOptions, progress: Progress):
        self.service = service
        self.source = source
        self.options = options
        self.progress = progress
        self.owner = f"ingest-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.journal = Journal(service.store.data_dir)
        self.report = SkipReport(service.store.data_dir / "reports")
        self.summary = Summary()
        self._paths: dict[int, Path] = {}  # rows in flight -> their source file (for failures)

    def run(self) -> Summary:
        engine = make_engine(self.service, self.options.ray, self.options.workers, self.options.shared_fs)
        try:
            encode_and_complete(
                self.service, self._accepted(), engine, batch=self.options.batch, on_batch=self._completed
            )
        finally:
            engine.close()
            self.service.store.release(self.owner)  # rows not completed go back to the queue at once
            self.journal.close()
            self.report.close()
        self.summary.report = self.report.path if self.report.written else None
        return self.summary

    # -- reading and accepting ----------------------------------------------------------------------
    def _skip(self, path: Path | str, category: str, reason: str) -> None:
        self.summary.skipped[category] += 1
        self.report.add(path, reason)

    def _accepted(self) -> Iterator[EncodeItem]:
        """Accept the source chunk by chunk and yield the new rows to encode (the engine pulls lazily)."""
        with ThreadPoolExecutor(max_workers=max(1, self.options.workers)) as pool:
            for chunk in batched(self.source.items(), self.options.chunk):
                yield from self._accept_chunk(chunk, pool)

    def _accept_chunk(self, chunk: Sequence[SourceItem], pool: ThreadPoolExecutor) -> list[EncodeItem]:
        keyed: list[tuple[SourceItem, FileKey]] = []
        for item in chunk:
            if item.problem is not None:
                self._skip(item.path, "bad row", item.problem)
                continue
            try:
                st = item.path.stat()
            except OSError as e:
                self._skip(item.path, *skip_reason(e))
                continue
            keyed.append((item, FileKey(str(item.path), st.st_size, st.st_mtime_ns)))
        hits = self.journal.lookup([k for _, k in keyed])
        alive = self.service.store.get_many(list(set(hits.values()))) if hits else {}
        todo = [(item, key) for item, key in keyed if hits.get(key.path) not in alive]
        self.summary.unchanged += len(keyed) - len(todo)
        results = list(pool.map(self._prepare, todo))
        ok = [(key, ref, item) for (item, key), ref in zip(todo, results, strict=True) if isinstance(ref, NewReference)]
        for (item, _), res in zip(todo, results, strict=True):
            if not isinstance(res, NewReference):
                self._skip(item.path, *res)
        self.progress.update(len(chunk) - len(ok))
        if not ok:
            return []
        accepted = self.service.accept_prepared([ref for _, ref, _ in ok])
        self.journal.record([(key, ref_id) for (key, _, _), ref_id in zip(ok, accepted.reference_ids, strict=True)])
        new = [n for n, dup in enumerate(accepted.duplicates) if not dup]
        self.summary.duplicates += len(ok) - len(new)
        self.progress.update(len(ok) - len(new))
        ids = [accepted.reference_ids[n] for n in new]
        if ids:
            self.service.store.claim(ids, self.owner, self.options.lease_s)
        self.summary.added += len(ids)
        ship = self.options.ray is not None and not self.options.shared_fs
        out = []
        for n, ref_id in zip(new, ids, strict=True):
            _, ref, item = ok[n]
            self._paths[ref_id] = item.path
            path = self.service.store.image_path_for(ref.sha256, ref.ext)
            out.append(EncodeItem(ref_id, path, ref.image if ship else None, self.service.thumbnail_px))
        return out

    def _prepare(self, pair: tuple[SourceItem, FileKey]) -> NewReference | tuple[str, str]:
        """Read and validate one file (the API's limits); a bad file gives (category, reason), never raises."""
        item, key = pair
        limits = self.service.limits
        if key.size > limits.max_bytes:  # refused on its size alone: never read
            return "too large", f"the file has {key.size} bytes; the limit is {limits.max_bytes}"
        try:
            data = read_regular(item.path, self.source.within, limits.max_bytes)
            upload = Upload(data, item.path.name, item.lat, item.lon, item.heading, item.captured_at, item.label)
            return prepare_upload(upload, limits, source=self.source.kind, exif_heading=self.source.exif_heading)
        except (OSError, GeolocError) as e:
            return skip_reason(e)

    # -- completing ---------------------------------------------------------------------------------
    def _completed(self, results: Sequence[Encoded]) -> None:
        for r in results:
            path = self._paths.pop(r.ref_id, None)
            if r.error is not None:  # stored as a failed row (see GET /jobs); listed in the report too
                self.summary.failed += 1
                self.report.add(path or f"reference {r.ref_id}", f"encoding failed: {r.error}")
        self.service.store.release(self.owner, [r.ref_id for r in results])
        self.progress.update(len(results))


def ingest(
    service: GeolocService,
    source: Source,
    options: IngestOptions,
    say: Callable[[str], None] = print,
    progress: Progress | None = None,
) -> tuple[Summary, int]:
    """The whole of `geoloc ingest`: the run, and, when no server's worker holds the data dir (this run then
    holds the writer role, ``app.ingestion.writer``), the rows earlier runs left pending (crashed, or storage
    retries) and a final snapshot of the index kind the collection's size calls for. Returns the run's
    summary and how many of those rows it encoded.
    ``progress``: where the run counts its photos (default: a bar, or a log line per thousand)."""
    writer = Writer(service.store.backend, options.batch, workers=options.workers)
    writer.attach(service)
    if not writer.acquire():
        say("a server's worker runs on this data dir: this run encodes its own rows, the server follows")
    completed = False
    switches = service.collection.stats.kind_switches
    try:
        progress = progress or Progress(source.count(), desc=f"ingest {source.kind}")
        try:
            summary = IngestRun(service, source, options, progress).run()
        finally:
            progress.close()
        left = writer.drain(service)
        if writer.held:  # the final snapshot holds the kind the size calls for: the next start serves it at once
            service.index_at_size(say)
        if service.collection.stats.kind_switches > switches:  # here, or by a batch's catch-up meanwhile
            say(service.collection.last_switch)
        completed = True
    finally:
        writer.stop(final=completed)  # the snapshot (a completed run), the checkpoint, the lock
    return summary, left
