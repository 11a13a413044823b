"""The application's use cases over one data dir, for every face of the product (HTTP routes, the CLI, the
ingestion worker, the benchmarks): locate a photo, accept uploads (validated, then stored in bulk as pending
rows with their job), encode, complete, edit, delete, list, get.

``GeolocService.locate`` is the locate use case, whole, for /locate and `geoloc locate` alike; the search
itself is ``app.usecases.locate.locate_features``, which the evaluation calls too."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.domain import Accepted, LocateAnswer, LocateOptions, ReferenceEdit, Upload
from app.engine.calibration import Calibration
from app.engine.errors import InvalidPosition
from app.engine.geo import valid_position
from app.engine.imageio import ImageLimits, LoadedImage
from app.engine.pipeline import Features, Pipeline
from app.errors import InvalidRequest
from app.ingestion.thumbnails import THUMBNAIL_PX, thumbnail
from app.ingestion.uploads import metadata_differences, prepare_upload
from app.policies import IndexSizing, SnapshotPolicy
from app.runtime import release_free_memory
from app.storage.backend import Listener, StorageBackend
from app.storage.feature_files import FeatureFiles, profile_root
from app.storage.queue import Job
from app.storage.shared_images import check_images_shared
from app.storage.store import KeysetPage, NewReference, Reference, ReferenceStore
from app.usecases.collection import Collection, IndexStats
from app.usecases.locate import StoredReferenceFeatures, StoreReferences, locate_features

log = logging.getLogger("geoloc.core")


def extraction_slots(concurrency: int) -> AbstractContextManager:
    """How many locates may decode and extract at once (0: no limit). Each holds a decoded photo and its
    feature maps meanwhile; the limit bounds that memory. One per usable CPU by default: with no
    limit, concurrent uploads of large photos each hold a full decode at once (bench/locate_memory.py).
    Throughput pays a little (bench/load.py; docs/benchmarks.md)."""
    return threading.BoundedSemaphore(concurrency) if concurrency else nullcontext()


@dataclass(frozen=True)
class Readiness:
    """What /ready tells a caller with the key about the loaded collection."""

    config: str
    index_size: int
    version: int
    generation: int
    database: str  # the storage backend's name
    index_loaded: str  # "shared" (a shared index server), "rebuilt" (from the database) or "snapshot"
    index: dict[str, dict[str, Any]]  # each part's kind and parameters
    index_choice: str
    calibration: str


@dataclass(frozen=True)
class Gauges:
    """What /metrics reads from the live collection at scrape time."""

    index: dict[str, dict[str, Any]]  # each part's kind, size and parameters
    pending: int  # rows accepted and not encoded yet (the queue's depth)
    version: int
    tombstones: int
    switching: bool  # a compressed index is being built in the background
    upkeep: IndexStats


# -- the service ------------------------------------------------------------------------------------------
class GeolocService:
    """The use cases over one data dir. Thread-safe: the HTTP layer calls it from a thread pool."""

    def __init__(
        self,
        collection: Collection,
        limits: ImageLimits | None = None,
        keep_queries: bool = False,
        locate_concurrency: int = 0,
        thumbnail_px: int = THUMBNAIL_PX,
    ):
        self.collection = collection
        self.thumbnail_px = thumbnail_px  # references' thumbnails: made at encoding, served by ``thumbnail``
        self.limits = limits or ImageLimits()
        self.keep_queries = keep_queries
        self.refs = StoreReferences(collection.store)
        #: Taken by each locate while it reads, decodes and extracts (``extraction_slots``).
        self.extract_slots = extraction_slots(locate_concurrency)

    @classmethod
    def open(
        cls,
        data_dir: Path,
        models_dir: Path,
        config: str | None,
        limits: ImageLimits | None = None,
        policy: SnapshotPolicy | None = None,
        keep_queries: bool = False,
        locate_concurrency: int = 0,
        thumbnail_px: int = THUMBNAIL_PX,
        backend: StorageBackend | None = None,
        sizing: IndexSizing | None = None,
    ) -> GeolocService:
        """``backend``: made once from the process's Settings (``Settings.backend``) and passed down; ``sizing``:
        when the index switches to the compressed kinds (``Settings.index_sizing``)."""
        collection = Collection.open(data_dir, models_dir, config, policy, backend, sizing)
        return cls(collection, limits, keep_queries, locate_concurrency, thumbnail_px)

    @property
    def store(self) -> ReferenceStore:
        return self.collection.store

    @property
    def pipeline(self) -> Pipeline:
        return self.collection.pipeline

    # -- what the faces ask about the data dir and its collection ------------------------------------------
    @property
    def data_dir(self) -> Path:
        return self.store.data_dir

    @property
    def config_name(self) -> str:
        """The name of the configuration this collection is served with."""
        return self.pipeline.config.name

    @property
    def size(self) -> int:
        """How many references the index holds (as this process last caught up)."""
        return self.collection.size

    def pending(self) -> int:
        """How many accepted rows wait for the worker."""
        return self.store.count("pending")

    @property
    def write_refusal(self) -> str | None:
        """Why the storage refuses writes (its database files changed under this process), or None."""
        return self.store.write_refusal

    def index_at_size(self, report: Callable[[str], None], stop: threading.Event | None = None) -> bool:
        """Make the index the kind the collection's size calls for before serving or ending a bulk load
        (``Collection.index_at_size``), saying what it does through ``report``; ``stop`` ends the wait."""
        return self.collection.index_at_size(report, stop=stop)

    def snapshot_at_size(self, report: Callable[[str], None]) -> bool:
        """After this process built the index its size calls for and before it serves: that index's snapshot
        written now, by the writer role's holder (the caller), so that the write of a large index does not run
        beside the first requests and a restart loads it. Returns whether one was due."""
        col = self.collection
        if not col.stats.kind_switches or not col.snapshot_due():
            return False
        report(f"writing the snapshot of the index ({col.size:,} references)")
        col.write_snapshot()  # waits for the writer's own snapshot thread where it began the same write
        return True

    def readiness(self) -> Readiness:
        """The collection's state for /ready, caught up first."""
        col = self.collection
        col.catch_up()
        return Readiness(
            config=col.pipeline.config.name,
            index_size=col.size,
            version=col.version,
            generation=col.generation,
            database=self.store.engine,
            index_loaded="shared" if col.shared is not None else "rebuilt" if col.stats.full_rebuilds else "snapshot",
            index=col.index.stats(),
            index_choice=col.index_choice(),
            calibration=col.calibration_summary(),
        )

    def gauges(self) -> Gauges:
        """The collection's state for /metrics, caught up first; one index read for its parts and tombstones."""
        col = self.collection
        col.catch_up()
        idx = col.index
        return Gauges(
            index=idx.stats(),
            pending=self.pending(),
            version=col.version,
            tombstones=idx.tombstones,
            switching=col.switching,
            upkeep=col.stats,
        )

    def check_images_shared(self) -> None:
        """On a backend that hosts share (PostgreSQL): ``ImagesNotShared`` unless this host's images folder is
        the one the others use (``app.storage.shared_images``)."""
        check_images_shared(self.store)

    def start_change_listener(self) -> Listener | None:
        """Where other hosts commit changes (PostgreSQL): a started listener that catches this collection up
        as they do, rather than at the next search; None where processes catch up at their next search."""
        listener = self.store.backend.change_listener(self.collection.catch_up)
        return listener.start() if listener is not None else None

    def close(self) -> None:
        """Close the store: on SQLite, a checkpoint puts the rows this process wrote into the main file."""
        self.store.close()

    # -- locate ---------------------------------------------------------------------------------------
    def decode(self, data: bytes) -> LoadedImage:
        """At the scale the pipeline needs (``Pipeline.decode``), under the service's limits."""
        return self.pipeline.decode(data, self.limits)

    def _extract(self, data: bytes) -> tuple[LoadedImage, Features, float]:
        """Decode and extract (the expensive, parallel part of a request); returns the decode time too."""
        t0 = time.perf_counter()
        img = self.decode(data)
        decode_ms = (time.perf_counter() - t0) * 1000
        features = self.pipeline.extract(img.rgb)
        self.release_memory(img)  # the decode and extraction buffers, before the next request in this slot
        return img, features, decode_ms

    def release_memory(self, img: LoadedImage) -> None:
        """After a large upload (decoded at reduced scale, a PNG at full size first), hand the buffers it
        freed back to the kernel: glibc keeps them in per-thread arenas, and with the server's thread pool
        concurrent large uploads left RSS far above idle for good (bench/locate_memory.py)."""
        if max(img.original_size) > 2 * self.limits.decode_long_side:
            release_free_memory()

    def _locate_extracted(self, img: LoadedImage, features: Features, options: LocateOptions) -> LocateAnswer:
        """Search with one generation's pipeline and index taken together (a re-fit may swap them at any
        moment); features extracted under another configuration are extracted again."""
        col = self.collection
        col.catch_up()
        view = col.view()
        view.check_mode(options.mode)
        if features.config is not None and features.config != view.pipeline.config.name:
            features = view.pipeline.extract(img.rgb)
        calibration = col.calibration(view.pipeline)
        profile = view.pipeline.config.stored_features
        stored = None
        if profile is not None:
            stored = StoredReferenceFeatures(self.store, FeatureFiles(profile_root(self.store.data_dir, profile)))
        answer = locate_features(
            view.pipeline,
            view,
            self.refs,
            features,
            options,
            img.rgb,
            self.limits,
            calibration=calibration,
            stored=stored,
        )
        answer.index_size, answer.index_generation = view.index.size, view.generation
        answer.index_version = col.version if col.generation == view.generation else 0
        answer.extent = col.store.extent()
        return answer

    def locate(self, image: bytes | Callable[[], bytes], options: LocateOptions) -> LocateAnswer:
        """The locate use case, whole: a bad mode is refused before the expensive part; the photo is read,
        decoded, extracted, searched and verified holding an extraction slot; the search runs with one
        generation's pipeline and index; the query is kept when asked; freed memory goes back to the kernel,
        once the request holds nothing large. ``image``: the photo's bytes, or a function that reads them (a
        request body, read only once a slot is free; the wait for it is timed as ``queue``)."""
        t0 = time.perf_counter()
        self.collection.check_mode(options.mode)
        # Everything the request does holds its slot: verification (``rerank``) decodes and extracts each
        # candidate's photo, and outside the slot any number of such requests would hold their photos at once.
        with self.extract_slots:
            t_slot = time.perf_counter()
            data = image() if callable(image) else image
            img, features, decode_ms = self._extract(data)
            answer = self._locate_extracted(img, features, options)
            self.keep_query(data, img)
            self.release_memory(img)  # what the search freed too
        queue = {"queue": (t_slot - t0) * 1000} if callable(image) else {}
        timings = {**queue, "decode": decode_ms, **answer.timings_ms}
        timings["total"] = (time.perf_counter() - t0) * 1000
        answer.timings_ms = timings
        return answer

    def answer_calibration(self, options: LocateOptions) -> Calibration:
        """The rule that judges this collection's answers located with ``options``, as ``locate_features``
        picks it: the verified one for verified answers, the conservative one in a non-default mode."""
        view = self.collection.view()
        verify = options.rerank if options.rerank is not None else view.pipeline.config.stored_features is not None
        calibration = self.collection.calibration(view.pipeline).for_answer(verify)
        if view.check_mode(options.mode) != view.check_mode(None) and calibration.calibrated:
            return Calibration.conservative(f"this collection is calibrated for {view.check_mode(None)} search")
        return calibration

    def keep_query(self, data: bytes, img: LoadedImage) -> None:
        if not self.keep_queries:
            return
        from app.permissions import private_dir
        from app.storage.files import sha256_of, write_image_file

        try:
            folder = self.store.data_dir / "queries"
            private_dir(folder)
            write_image_file(folder / f"{sha256_of(data)}.{img.format.lower()}", data, sync=False)  # 0600
        except OSError as e:  # keeping queries is a courtesy; a full disk must not fail the answer
            log.warning("query not kept: %s", e)

    # -- accept (the queued rows are encoded and completed by app.ingestion.completion) ----------------
    def accept(self, uploads: Sequence[Upload], source: str = "api") -> Accepted:
        """Validate every upload, then store them all (images durable, rows and job in one transaction) as
        pending rows. The index is not touched: the worker encodes them."""
        prepared = [prepare_upload(u, self.limits, n, source) for n, u in enumerate(uploads)]
        return self.accept_prepared(prepared, uploads)

    def accept_prepared(self, prepared: Sequence[NewReference], asked: Sequence[Upload] | None = None) -> Accepted:
        """Store; for identical images already stored, say when the upload's metadata was not applied."""
        items, job_id = self.store.add_many(prepared, job=True)
        dups = [(n, i) for n, (i, created) in enumerate(items) if not created]
        stored = self.store.get_many([i for _, i in dups]) if dups else {}
        notes = []
        for n, ref_id in dups:
            upload = asked[n] if asked is not None else None
            diff = metadata_differences(prepared[n], stored[ref_id], upload) if ref_id in stored else []
            if diff:
                notes.append(
                    f"image {n} is already stored as reference {ref_id}; its stored metadata was kept: "
                    + "; ".join(diff)
                    + f". To change it: PATCH /references/{ref_id}"
                )
        return Accepted(job_id, [i for i, _ in items], [not created for _, created in items], notes)

    def update(self, ref_id: int, edit: ReferenceEdit) -> Reference | None:
        """Edit a reference's metadata (validated here; codes and image unchanged)."""
        fields = edit.given
        if any(name in fields and fields[name] is None for name in ("lat", "lon")):
            raise InvalidRequest("lat and lon cannot be cleared, only changed")
        if not fields:
            raise InvalidRequest("give at least one of lat, lon, heading, label, captured_at")
        current = self.store.get(ref_id)
        if current is None:
            return None
        lat, lon = fields.get("lat", current.lat), fields.get("lon", current.lon)
        if lat is None or lon is None or not valid_position(lat, lon):
            raise InvalidPosition(f"position {lat},{lon} is out of range (lat -90..90, lon -180..180)")
        hd = fields.get("heading")
        if hd is not None and not (math.isfinite(hd) and 0 <= hd < 360):
            raise InvalidRequest("heading must be a number in [0, 360)")
        return self.store.update(ref_id, fields)

    # -- the rest ---------------------------------------------------------------------------------------
    def delete(self, ref_id: int) -> str | None:
        """None: no such reference; else whether its image file is ``"removed"`` or its removal ``"queued"``
        (the reference is gone either way: see ``ReferenceStore.delete``)."""
        outcome = self.store.delete(ref_id)
        if outcome is not None:
            self.collection.catch_up()  # gone from this process's searches at once
        return outcome

    def get(self, ref_id: int) -> Reference | None:
        return self.store.get(ref_id)

    def list(self, offset: int, limit: int, bbox=None) -> tuple[list[Reference], int]:
        return self.store.list(offset, limit, bbox)

    def page(self, after: int | None, before: int | None, limit: int, bbox=None) -> KeysetPage:
        return self.store.page(after, before, limit, bbox)

    def count_in(self, bbox=None) -> int:
        return self.store.count_in(bbox)

    def job(self, job_id: str) -> Job | None:
        return self.store.job(job_id)

    def image_path(self, ref_id: int) -> Path | None:
        return self.store.image_path(ref_id)

    def thumbnail(self, ref_id: int) -> bytes | None:
        """The reference's JPEG thumbnail (``app.ingestion.thumbnails``); None when there is no such reference.
        FileNotFoundError when its stored image is gone."""
        path = self.store.image_path(ref_id)
        return None if path is None else thumbnail(path, self.thumbnail_px, self.limits)
