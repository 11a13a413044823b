"""The FastAPI app factory. Loading (model, fitted pipeline, index) runs in a background thread started by
the lifespan, so /health answers at once and /ready says 503 until everything is loaded."""

from __future__ import annotations

import logging
import os
import threading
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from app import __version__, apikey
from app.api import docs, errors, security
from app.api.limits import BodyLimits
from app.api.metrics import Metrics, MetricsMiddleware
from app.api.routes import ROUTERS, ROUTES
from app.engine.index.faiss_index import set_search_threads
from app.ingestion.worker import IngestWorker
from app.ingestion.writer import Writer
from app.runtime import serving_blas_threads
from app.settings import Settings, usable_cpus
from app.usecases.service import GeolocService

log = logging.getLogger("geoloc.api")
#: The page (drop a photo, see where it was taken). Leaflet and Swagger UI are copied into vendor/ by
#: `make setup` from the npm registry, never loaded from a CDN.
WEB_DIR = Path(__file__).resolve().parents[1] / "web" / "static"
#: The back-fill thread's niceness (0-19; higher yields more): requests first, the back-fill with what is left.
BACKFILL_NICE = 10


def _run_writer(app: FastAPI, service: GeolocService) -> None:
    """The in-process worker: the writer role (``app.ingestion.writer``) now, or, while another process (a server
    or `geoloc worker`) holds the data dir's worker lock, a retry every GEOLOC_WORKER_RETRY_SECONDS that takes
    the role over once that process is gone (failover: uploads accepted here are still indexed)."""
    state = app.state
    s: Settings = state.settings
    m = state.metrics

    def count(indexed: int, failed: int) -> None:
        m.ingested.labels("indexed").inc(indexed)
        m.ingested.labels("failed").inc(failed)

    def started(worker: IngestWorker) -> None:
        state.worker = worker  # /ready says in-process once everything runs

    writer = Writer(s.backend(s.data_dir), s.worker_batch, on_batch=count, logger=log, max_attempts=s.encode_attempts)
    state.writer = writer
    if not writer.start(service, retry_seconds=s.worker_retry_seconds, on_started=started):
        log.warning(
            "another worker holds %s: this process serves searches and accepts uploads, and takes the worker "
            "over if that one stops",
            writer.lock.where,
        )


def _not_ready(app: FastAPI, line: str) -> None:
    """What /ready says until the service is ready; each new line goes to the log too."""
    if line != app.state.not_ready:
        log.info("%s", line)
    app.state.not_ready = line


def _first_start(app: FastAPI) -> None:
    """An empty data dir is fitted on GEOLOC_INITIAL_PHOTOS and they are ingested (``app.jobs.first_start``),
    before it is opened; each progress line goes to the log and is what /ready says meanwhile."""
    from app.jobs.first_start import run_first_start

    s: Settings = app.state.settings
    workers = min(4, usable_cpus())  # extraction threads; each holds one decoded photo
    run_first_start(
        s.data_dir,
        s.models_dir,
        s.config,
        s.initial_photos,
        lambda line: _not_ready(app, line),
        s.image_limits(),
        workers=workers,
        backend=s.backend(s.data_dir),
        disc={"radius_rate": s.radius_rate, "max_radius_m": s.max_radius_m},
    )


def _backfill(app: FastAPI, stop: threading.Event) -> None:
    """A data dir whose configuration stores local features but whose references lack some (made before it
    stored them, restored from a backup without them) gets them in the background
    (``app.ingestion.backfill``, what `geoloc features backfill` runs), while answers verify the
    candidates that have a file and leave the rest unverified. /ready shows the walk's latest line."""
    from app.ingestion.backfill import PAGE, backfill_stored_features, needed

    state = app.state
    s: Settings = state.settings
    backend = s.backend(s.data_dir)
    if needed(s.data_dir, s.config, backend) is None:
        return
    every, lines = 10, 0  # /ready's line moves every 10 references; the log gets one every PAGE

    def say(line: str) -> None:
        nonlocal lines
        state.backfill = line
        lines += 1
        last = not line.endswith(" failed")  # done, stopped, or left to another process
        if last or lines % (PAGE // every) == 1:
            log.info("%s", line)

    def walk() -> None:
        # Below the requests: this thread, and the onnxruntime threads its extractor's session starts, run
        # at a lower priority (Linux nices threads one by one; new threads inherit it).
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), BACKFILL_NICE)
        try:
            backfill_stored_features(
                s.data_dir, s.models_dir, s.config, s.image_limits(), say, every, stop, wait=False, backend=backend
            )
        except Exception as e:  # the service keeps answering; a restart tries again
            log.exception("stored features backfill failed")
            state.backfill = f"features backfill failed: {e} (the next start tries again)"

    state.backfill = "features backfill: starting"
    state.backfill_thread = threading.Thread(target=walk, name="geoloc-backfill", daemon=True)
    state.backfill_thread.start()


def _load(app: FastAPI, stop: threading.Event) -> None:
    """Load until it works: a missing model or an unreadable data dir may be fixed while we wait, so
    loading retries with backoff and /ready says why meanwhile (never a permanent 503)."""
    state = app.state
    s: Settings = state.settings
    delay = 1.0
    while not stop.is_set():
        try:
            if s.initial_photos is not None:
                _first_start(app)
            service = GeolocService.open(
                s.data_dir,
                s.models_dir,
                s.config,
                s.image_limits(),
                s.snapshot_policy(),
                s.keep_queries,
                s.locate_concurrency,  # the extraction slots: app/usecases/service.py, extraction_slots
                s.thumbnail_px,
                s.backend(s.data_dir),
                s.index_sizing(),
            )
            try:
                service.check_images_shared()  # on PostgreSQL: one images folder for every host
            except Exception:  # refused, or the check could not run: this service is not used
                service.close()
                raise
            # Ready means ready at size: a data dir left exact above the switch (a bulk load, a restore
            # without a snapshot) is not served by the slow exact search; /ready says how far the build is.
            built = service.index_at_size(lambda line: _not_ready(app, line), stop)
            if stop.is_set():  # shutting down while it built: nothing to serve
                service.close()
                return
            if not built:
                log.warning("the index its size calls for could not be built: the exact index serves")
            if s.worker == "inprocess":
                _run_writer(app, service)
                if state.writer.held:
                    service.snapshot_at_size(lambda line: _not_ready(app, line))
            # Where other hosts commit changes (PostgreSQL): catch up as they do, not at the next search.
            listener = service.start_change_listener()
            if listener is not None:
                state.listener = listener
            state.service = service
            state.not_ready = None
            log.info("ready: config %s, %d references", service.config_name, service.size)
            _backfill(app, stop)
            return
        except Exception as e:  # keep /health up and say what is wrong on /ready
            log.exception("loading failed; retrying in %.0f s", delay)
            state.not_ready = f"loading failed: {e} (retrying in {delay:.0f} s)"
            stop.wait(delay)
            delay = min(delay * 2, 30.0)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        serving_blas_threads(settings.blas_threads)
        set_search_threads(settings.faiss_threads)
        stop = threading.Event()
        loader = threading.Thread(target=_load, args=(app, stop), name="geoloc-load", daemon=True)
        loader.start()
        yield
        stop.set()
        loader.join(timeout=60)
        if app.state.backfill_thread is not None:  # stops between two references
            app.state.backfill_thread.join(timeout=60)
        if getattr(app.state, "library", None) is not None:  # its scans stop between two photos
            app.state.library.close()
        if app.state.listener is not None:
            app.state.listener.stop()
        if app.state.writer is not None:  # the worker, the final snapshot and checkpoint, the lock
            app.state.writer.stop()
        if app.state.service is not None:
            app.state.service.close()  # checkpoints: the rows this process wrote go into the main file

    app = FastAPI(
        title="geoloc",
        version=__version__,
        description="Visual geolocation: find where a photo was taken by recognising the place in geotagged "
        'reference images.\n\nErrors are JSON: `{"error": code, "message": text}`; the codes are a frozen '
        "list (never renamed):\n\n" + errors.codes_markdown(),
        lifespan=lifespan,
        docs_url=None,  # served by app/api/docs.py from local files, not from a CDN
        redoc_url=None,  # off: see app/api/docs.py
    )
    app.state.settings = settings
    #: Resolved once, before the first request: the environment's key, none (--no-auth), or the data dir's.
    app.state.api_key = apikey.resolve(settings.api_key, settings.no_auth, settings.data_dir)
    app.state.metrics = Metrics()
    app.state.service = None
    app.state.listener = None  # the backend's change listener, where it has one (PostgreSQL)
    app.state.writer = None  # the writer role (worker=inprocess), held or waiting for the worker lock
    app.state.worker = None  # its ingestion worker, once this process holds the role
    app.state.not_ready = None
    app.state.backfill = None  # the stored features' back-fill: its latest progress line (/ready)
    app.state.backfill_thread = None
    # Each add wraps the ones before (the last is outermost): a bug still answers JSON and keeps the
    # connection; body limits and keys come before any body is read; metrics see every answer.
    app.add_middleware(errors.LastResort)
    app.add_middleware(BodyLimits, settings=settings, routes=ROUTES)
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)
    app.add_middleware(security.HtmlPolicy)  # outermost: every answer, refusals included, gets its headers
    backend = settings.backend(settings.data_dir)
    errors.install(app, backend.exceptions, backend.unavailable)
    for router in ROUTERS:
        app.include_router(router)
    app.mount("/static", StaticFiles(directory=WEB_DIR), name="static")
    docs.install(app, WEB_DIR)

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        return FileResponse(WEB_DIR / "index.html", headers=security.PAGE_HEADERS)

    return app
