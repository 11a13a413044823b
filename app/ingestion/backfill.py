"""``geoloc features backfill``: make the stored local features a data dir's indexed references lack.

Why: the encode path writes a reference's file as it encodes it, but a data dir can hold references without
one (ingested by a version that stored none, a file lost, a crash between the file and its row); those are
found but never verified. This walks the references in id order, a page at a time (never all of them in
memory), and makes each missing file from the stored image with the same decode and extractor the encode
path uses, so a back-filled file is the file ingestion would have written.

Resumable by construction: a file that exists and reads back intact is done, so an interrupted run started
again skips what the last one wrote and goes on. Intact, not only there: a damaged file (emptied, truncated,
bit-flipped) exists too, and only a walk that reads it (its CRC) remakes it; one file is read at a time.
Safe beside a running service: files are written atomically, and a reference deleted meanwhile has its
file removed again (its image's removal may have run before the file existed).

Two callers, one walk: ``geoloc features backfill`` (the operator's command) and the server, which starts it
in the background when it opens a data dir whose configuration stores features and whose last walk did not
finish (``needed``: no ``.backfilled`` marker in the profile's folder, so a data dir made before the
configuration stored features, or restored from a backup without them). The marker is written once a walk
has looked at every reference; from then on the encode path writes every new reference's file, so a
restart costs no walk over the collection. One walk at a time per data dir (a lock file beside the marker):
a second server, or the command while a server walks, waits for it or leaves it to the walker.
"""

from __future__ import annotations

import fcntl
import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from app.engine.added_models import register_added_models
from app.engine.configs import DEFAULT_CONFIG, get_config
from app.engine.errors import GeolocError
from app.engine.imageio import ImageLimits
from app.engine.pipeline import Pipeline
from app.engine.stored_features import encode
from app.errors import OperationRefused
from app.permissions import private_dir
from app.storage.backend import StorageBackend
from app.storage.feature_files import FeatureFiles, damage, profile_root
from app.storage.files import write_image_file
from app.storage.store import ReferenceStore

PAGE = 500
#: In the profile's folder: a walk looked at every reference (its report, as JSON). ``needed`` reads it.
MARKER = ".backfilled"
LOCK = ".backfill.lock"


@dataclass
class BackfillReport:
    profile: str
    total: int = 0  # indexed references when the walk started (the progress's denominator)
    seen: int = 0  # indexed references looked at
    present: int = 0  # already had an intact file (done by ingestion or an earlier run)
    written: int = 0
    repaired: int = 0  # of ``written``: in place of a file that was there but failed its check (damaged)
    failed: int = 0  # image missing or undecodable: left without a file (``geoloc check`` names them)
    stopped: bool = False  # asked to stop before the end (the server stopping): the next walk resumes
    skipped: bool = False  # another process was walking this data dir (``wait=False``): left to it


def needed(data_dir: Path, config: str | None, backend: StorageBackend | None = None) -> str | None:
    """The profile a walk should fill, or None: the data dir's configuration stores no features, or a walk
    over this profile finished (its marker). A cheap question for every start: one row, one stat."""
    store = ReferenceStore(data_dir, read_only=True, backend=backend)
    try:
        profile = get_config(store.get_meta("config") or config or DEFAULT_CONFIG).stored_features
    finally:
        store.close()
    if profile is None or (profile_root(data_dir, profile) / MARKER).is_file():
        return None
    return profile


def backfill_stored_features(
    data_dir: Path,
    models_dir: Path,
    config: str | None = None,
    limits: ImageLimits | None = None,
    say: Callable[[str], None] = print,
    every: int = PAGE,
    stop: threading.Event | None = None,
    wait: bool = True,
    backend: StorageBackend | None = None,
) -> BackfillReport:
    """Write the missing files of the data dir's configuration's profile; ``say`` gets a progress line every
    ``every`` references and at the end. ``stop`` (set by a stopping server) ends the walk between two
    references; the next one resumes. ``wait``: when another process is walking this data dir, wait for it
    (then look again: it may have done everything) or, if False, leave it the work (``skipped``)."""
    store = ReferenceStore(data_dir, read_only=True, backend=backend)  # rows are only read; files beside them
    try:
        name = store.get_meta("config") or config or DEFAULT_CONFIG
        register_added_models(models_dir)
        cfg = get_config(name)
        if cfg.stored_features is None:
            raise OperationRefused(
                f"configuration {name} stores no local features: nothing to back-fill (a configuration that "
                "stores them, such as lite2-hybrid-384-sv, writes them as it encodes)"
            )
        files = FeatureFiles(profile_root(store.data_dir, cfg.stored_features))
        report = BackfillReport(cfg.stored_features)
        with _WalkLock(files.root, wait, say) as held:
            if not held:
                report.skipped = True
                return report
            pipeline = Pipeline(cfg, models_dir=models_dir)  # only its decode and stored extractor are used
            pipeline.stored_extractor.load()
            _walk(store, pipeline, files, (limits or ImageLimits()).stored(), report, say, every, stop)
        return report
    finally:
        store.close()


def _walk(
    store: ReferenceStore,
    pipeline: Pipeline,
    files: FeatureFiles,
    limits: ImageLimits,
    report: BackfillReport,
    say: Callable[[str], None],
    every: int,
    stop: threading.Event | None,
) -> None:
    report.total = store.count("indexed")
    after = None
    while True:
        page = store.page(after=after, limit=PAGE)
        for ref in page.items:
            if stop is not None and stop.is_set():
                report.stopped = True
                say(_progress(report) + " (stopped: the next run resumes)")
                return
            if ref.status != "indexed":
                continue
            report.seen += 1
            data = files.read(ref.sha256)
            if data is not None and damage(data) is None:
                report.present += 1
            else:
                before = report.written
                _make_one(store, pipeline, files, ref.id, ref.sha256, limits, report)
                report.repaired += data is not None and report.written > before
            if report.seen % every == 0:
                say(_progress(report))
        if page.next_after is None:
            break
        after = page.next_after
    # Every reference looked at: from here on the encode path writes each new one's file.
    record = {**asdict(report), "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    write_image_file(files.root / MARKER, json.dumps(record).encode(), True)  # the same atomic write
    say(_progress(report) + " (done)")


class _WalkLock:
    """An exclusive flock on ``<profile folder>/.backfill.lock`` for the walk: ``__enter__`` says whether it
    is held (False only with ``wait=False`` while another process holds it)."""

    def __init__(self, root: Path, wait: bool, say: Callable[[str], None]):
        self.root, self.wait, self._say, self._fd = root, wait, say, -1

    def __enter__(self) -> bool:
        private_dir(self.root, parents=True)
        self._fd = os.open(self.root / LOCK, os.O_CREAT | os.O_RDWR, 0o600)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            if not self.wait:
                self._say(f"features backfill ({self.root.name}): another process is back-filling; left to it")
                return False
            self._say(f"features backfill ({self.root.name}): another process is back-filling; waiting for it")
            fcntl.flock(self._fd, fcntl.LOCK_EX)
        return True

    def __exit__(self, *exc: object) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)


def _make_one(
    store: ReferenceStore,
    pipeline: Pipeline,
    files: FeatureFiles,
    ref_id: int,
    sha: str,
    limits: ImageLimits,
    report: BackfillReport,
) -> None:
    path = store.image_path(ref_id)
    try:
        data = path.read_bytes() if path is not None else None
        if data is None:
            raise FileNotFoundError(ref_id)
        record = pipeline.stored_extractor.record(pipeline.decode(data, limits).rgb)
    except (OSError, GeolocError):
        report.failed += 1
        return
    files.write(sha, encode(record))
    if not store.named_files([path.name]):  # deleted meanwhile: no file outlives its image
        files.delete(sha)
        return
    report.written += 1


def _progress(r: BackfillReport) -> str:
    return (
        f"features backfill ({r.profile}): {r.seen}/{r.total} indexed references, {r.written} written"
        + (f" ({r.repaired} of them in place of a damaged file)" if r.repaired else "")
        + f", {r.present} already there, {r.failed} failed"
    )
