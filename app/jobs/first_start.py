"""The first start of an empty data dir (``GEOLOC_INITIAL_PHOTOS``): fit the pipeline on the user's photos,
then ingest them, while the server already answers /health, and /ready says which step it is at.

Why: a user with Docker alone has no ``make fit`` and no fitted pipeline; the image holds the models, and
the data volume starts empty. So the server's loader (``app.api.app``) calls ``run_first_start`` before it
opens the data dir: the fit is ``app.usecases.fitting.fit_pipeline`` (what `geoloc fit` runs), saved in the data dir
as generation 0 (``pipelines/<config>-g0``, the layout a later `geoloc refit` continues from), and the photos
go in through the ingest use case (``app.ingestion.bulk.ingest``, what `geoloc ingest` runs). Nothing here
is a second fit or ingest path.

Restarts: the pipeline folder is written atomically and recorded only while the data dir has no pipeline
and no reference; an interrupted ingest is continued by the next start (the ingest journal skips the
photos already stored); meta ``first_start`` = ``done`` ends it for good, so a data dir is never refitted
or re-ingested from the folder behind the user's back.
"""

from __future__ import annotations

import fcntl
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from app.engine.imageio import ImageLimits
from app.engine.pipeline import Pipeline
from app.engine.progress import Progress
from app.errors import FitRefused, ServiceError
from app.ingestion.sources import Source, SourceItem, open_source
from app.permissions import private_dir
from app.storage.backend import StorageBackend
from app.storage.sqlite import SqliteBackend
from app.storage.store import ReferenceStore
from app.usecases.extraction import Counter
from app.usecases.fitting import FitProgress

log = logging.getLogger("geoloc.first_start")

#: Meta key: absent (never started), ``started`` (fitting, or fitted and ingesting) or ``done``.
STATE_KEY = "first_start"
STEPS = 3  # extract features for the fit, fit, ingest
#: Photos the fit learns from, at most (a seeded sample of a larger folder; `geoloc refit` uses the same).
FIT_SAMPLE = 2000


class FirstStartError(ServiceError):
    """The first start cannot go on (no usable photos, say); /ready shows the message and the loader
    retries, so adding photos to the folder is enough to fix it."""

    code = "not_ready"


def needed(data_dir: Path, backend: StorageBackend | None = None) -> bool:
    """Whether the data dir still needs its first start: nothing stored yet, or a first start not finished.
    ``backend``: the process's (``Settings.backend``; None: SQLite in ``data_dir``)."""
    backend = backend or SqliteBackend(data_dir)
    if not backend.exists():
        return True
    store = ReferenceStore(data_dir, backend=backend)
    try:
        state = store.get_meta(STATE_KEY)
        if state == "done":
            return False
        if state is not None:
            return True
        return store.get_meta("pipeline") is None and store.count(None) == 0
    finally:
        store.close()


def run_first_start(
    data_dir: Path,
    models_dir: Path,
    config: str,
    photos: Path,
    say: Callable[[str], None],
    limits: ImageLimits | None = None,
    workers: int = 1,
    seed: int = 0,
    backend: StorageBackend | None = None,
    disc: dict[str, float] | None = None,
) -> bool:
    """Fit and ingest when the data dir needs it (``needed``); ``say`` gets each progress line (the loader
    shows the latest on /ready and logs it). Returns whether anything was done.

    Two servers started on one empty volume (a scaled api) would both fit and the second would replace the
    first one's saved generation under codes already made with it: the first start holds a lock of its own
    (not the worker's, which its ingest step takes), and a process that waited for it looks again."""
    backend = backend or SqliteBackend(data_dir)
    if not needed(data_dir, backend):
        return False
    private_dir(Path(data_dir), parents=True)
    with _FirstStartLock(Path(data_dir) / "first_start.lock", say):
        if not needed(data_dir, backend):  # another process did it while this one waited
            return False
        return _run_first_start(data_dir, models_dir, config, photos, say, limits, workers, seed, backend, disc)


class _FirstStartLock:
    """An exclusive flock on a file in the data dir, held for the whole first start."""

    def __init__(self, path: Path, say: Callable[[str], None]):
        self.path, self._say, self._fd = path, say, -1

    def __enter__(self) -> _FirstStartLock:
        self._fd = os.open(self.path, os.O_CREAT | os.O_RDWR, 0o600)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._say("first start: another process is fitting this data dir; waiting for it")
            fcntl.flock(self._fd, fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc: object) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)


def _run_first_start(
    data_dir: Path,
    models_dir: Path,
    config: str,
    photos: Path,
    say: Callable[[str], None],
    limits: ImageLimits | None,
    workers: int,
    seed: int,
    backend: StorageBackend,
    disc: dict[str, float] | None = None,
) -> bool:
    limits = limits or ImageLimits()
    t0 = time.perf_counter()
    try:
        source = open_source(Path(photos))
    except ValueError as e:  # SourceError: missing folder, unreadable CSV
        raise FirstStartError(f"GEOLOC_INITIAL_PHOTOS: {e}") from None
    store = ReferenceStore(data_dir, backend=backend)
    try:
        if store.get_meta(STATE_KEY) is None:
            store.set_meta(STATE_KEY, "started")  # from here on, a restart continues this first start
        if store.get_meta("pipeline") is None:
            _fit(store, models_dir, config, source, say, limits, workers, seed, disc)
    finally:
        store.close()
    added = _ingest(data_dir, models_dir, config, source, say, limits, workers, backend)
    store = ReferenceStore(data_dir, backend=backend)
    try:
        store.set_meta(STATE_KEY, "done")
    finally:
        store.close()
    say(f"first start done in {time.perf_counter() - t0:.0f} s: {added} references from {photos}")
    return True


# -- steps 1 and 2: the fit ---------------------------------------------------------------------------------
def _sample(source: Source, seed: int) -> list[SourceItem]:
    items = [it for it in source.items() if it.problem is None]
    if len(items) > FIT_SAMPLE:
        keep = np.sort(np.random.default_rng(seed).choice(len(items), FIT_SAMPLE, replace=False))
        items = [items[i] for i in keep]
    return items


class _FitSteps(FitProgress):
    """The fit's progress, on /ready and in the log: step 1 (the extraction, with its rate) and step 2."""

    def __init__(self, say: Callable[[str], None], total: int):
        super().__init__()
        self._say, self._t0 = say, time.perf_counter()
        self._extracted(0, total)

    def extraction(self, total: int) -> Counter:
        return _Extracting(total, self._extracted)

    def _extracted(self, n: int, total: int) -> None:
        rate = f", {n / (time.perf_counter() - self._t0):.1f} photos/s" if n else ""
        self._say(
            f"first start: fitting the pipeline: step 1 of {STEPS}, extracting features ({n}/{total} photos{rate})"
        )

    def fitting(self, config: str, photos: int, extract_seconds: float) -> None:
        self._say(
            f"first start: fitting the pipeline: step 2 of {STEPS}, codebook, PCA and SVM bank on {photos} photos"
        )


class _Extracting:
    """Counts the photos extracted and tells every tenth of them (and the last) to ``tell``."""

    def __init__(self, total: int, tell: Callable[[int, int], None]):
        self.total, self.every, self.done, self._tell = total, max(1, total // 10), 0, tell

    def update(self, n: int) -> None:
        self.done += n
        if self.done % self.every == 0 or self.done == self.total:
            self._tell(self.done, self.total)

    def close(self) -> None:
        pass


def _fit(
    store: ReferenceStore,
    models_dir: Path,
    config: str,
    source: Source,
    say: Callable[[str], None],
    limits: ImageLimits,
    workers: int,
    seed: int,
    disc: dict[str, float] | None = None,
) -> None:
    """Fit (``app.usecases.fitting.fit_pipeline``) on a seeded sample of the photos, with the positions of their rows
    else of their EXIF (those with neither, or unreadable, are left out here and reported by the ingest
    step, which reads them again), and save it as generation 0."""
    from app.jobs.refit import save_generation
    from app.usecases.fitting import FitOptions, FitPhoto, bank_source, fit_pipeline
    from app.usecases.models import named_config

    cfg = named_config(config, models_dir)
    items = _sample(source, seed)
    if not items:
        raise FirstStartError(f"no photos in {source.path}: put geotagged photos (EXIF GPS) there")
    log.info("first start: fitting the %s pipeline on %d photos from %s", cfg.name, len(items), source.path)
    steps = _FitSteps(say, len(items))
    photos = [FitPhoto(it.path, lat=it.lat, lon=it.lon) for it in items]
    options = FitOptions(
        bank=bank_source(cfg, None),
        bank_optional=True,  # too small or too uniform for a bank: serve without one, and say so
        seed=seed,
        limits=limits,
        workers=workers,
        skip_unreadable=True,
        **(disc or {}),  # the disc every answer states: Settings.radius_rate, max_radius_m
    )
    pipe = Pipeline(cfg, models_dir=Path(models_dir))
    try:
        fitted = fit_pipeline(pipe, photos, options, steps)
    except FitRefused as e:
        raise FirstStartError(f"{source.path}: {e}") from None
    log.info("first start: fitted in %s", fitted.fit_seconds)
    extra = {"first_start": str(source.path), "fit_photos": len(fitted.refs), "svm_bank": fitted.bank}
    target = save_generation(store.data_dir, pipe, 0, extra)
    if not store.record_first_pipeline(target):
        raise FirstStartError(f"{store.data_dir} got a pipeline or references while the first start was fitting")
    log.info("first start: saved %s (SVM bank: %s)", store.data_dir / target.pipeline, fitted.bank)


# -- step 3: the ingest ------------------------------------------------------------------------------------
class _Reported(Progress):
    """The ingest's progress (a line every tenth of the photos in the log) that also tells the loader."""

    def __init__(self, total: int, say: Callable[[str], None], what: str):
        self._say, self._what = say, what
        super().__init__(total, desc="first start ingest", every=max(1, total // 10))

    def update(self, n: int) -> None:
        super().update(n)
        if n > 0:
            self._say(f"first start: {self._what} ({self.done}/{self.total} photos)")


def _ingest(
    data_dir: Path,
    models_dir: Path,
    config: str,
    source: Source,
    say: Callable[[str], None],
    limits: ImageLimits,
    workers: int,
    backend: StorageBackend,
) -> int:
    from app.ingestion.bulk import IngestOptions, ingest
    from app.usecases.service import GeolocService

    total = source.count()
    log.info("first start: ingesting the %d photos from %s", total, source.path)
    what = f"ingesting the photos: step 3 of {STEPS}"
    say(f"first start: {what} (0/{total} photos)")
    service = GeolocService.open(data_dir, models_dir, config, limits=limits, backend=backend)
    try:
        summary, _ = ingest(
            service, source, IngestOptions(workers=workers), say=log.info, progress=_Reported(total, say, what)
        )
    finally:
        service.close()
    skipped = sum(summary.skipped.values())
    log.info(
        "first start: %d references added, %d already present, %d failed, %d skipped%s",
        summary.added,
        summary.present,
        summary.failed,
        skipped,
        f" (report: {summary.report})" if summary.report else "",
    )
    return summary.added + summary.present
