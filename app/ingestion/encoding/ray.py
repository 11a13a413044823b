"""Encoding on a Ray cluster: a pool of encoder actors runs the same ``encode_item`` as the local engine.

Why actors (Ray Core) and not a Ray Data pipeline: the driver streams 10^5-10^6 pending rows from a
generator, ships their bytes and completes what comes back as it arrives. A Ray Data dataset needs its
rows up front (``from_items``) and builds a fresh actor pool per dataset, so streaming in windows would
reload the models every window; a fixed pool of actors loads them once per job, the driver keeps a bounded
number of batches in flight (``2 x workers``), and every wait is a ``ray.wait`` with a timeout, so a pool
that cannot be scheduled or a batch that never ends raises a clear error instead of hanging the job.

- Each actor holds 1 CPU, loads the fitted pipeline once (shipped through the object store unless the
  cluster shares the filesystem) and runs onnxruntime and OpenCV on 1 thread per CPU it holds.
- Actors restart after a crash (``max_restarts``) and their in-flight batches are retried
  (``max_task_retries``); a batch whose retries are spent raises, after every result that came back before
  it was yielded (the caller completes those, so a crash loses nothing: the rest stay pending rows).
- The driver is the one writer: it reads image bytes (without ``shared_fs``) and takes no CPU slot; the
  caller (``encode_and_complete``) completes results in batches.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

from app.engine.added_models import register_added_models
from app.engine.configs import get_config
from app.engine.imageio import ImageLimits
from app.engine.pipeline import PipelineSource
from app.errors import ServiceError
from app.ingestion.encoding.items import Encoded, EncodeItem, encode_item, read_item

log = logging.getLogger("geoloc.ray")

#: Seconds to start or reach Ray, and for the pool's actors to load their models.
START_TIMEOUT_S = 120.0
#: Seconds one batch may take before the job is declared stuck (a batch is a few images).
BATCH_TIMEOUT_S = 300.0
#: A ``ray://`` session runs on a server process the head starts for each client; on a busy head that
#: start fails now and then ("Starting Ray client server failed") and the next one, on the next port,
#: succeeds, so a client session is asked for this many times before the error reaches the user.
CLIENT_ATTEMPTS = 3
CLIENT_RETRY_PAUSE_S = 2.0
#: What the Ray Client's error says when the head started this client's server process and it died.
SESSION_START_FAILED = "Starting Ray client server failed"


class RayEngineError(ServiceError):
    """Ray could not be reached, the pool could not start, or a batch failed after its retries: the
    command's ``--ray`` address or cluster, not a bug (the CLI exits 2 with this line)."""

    code = "invalid_request"


def _import_ray():
    """Ray is an optional dependency: say how to get it instead of a bare ModuleNotFoundError."""
    try:
        import ray
    except ModuleNotFoundError:
        raise RayEngineError("encoding on Ray needs the ray extra: pip install 'geoloc[ray]'") from None
    return ray


# -- connecting --------------------------------------------------------------------------------------------
@contextmanager
def _deadline(timeout_s: float, what: str) -> Iterator[None]:
    """Raise ``RayEngineError`` if the block runs past ``timeout_s``: ``ray.init`` has no timeout of its own
    and must run on the main thread (started from another thread it loses its GCS connection), so the
    deadline is a SIGALRM timer there; elsewhere the block runs without one."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def expired(signum, frame):
        raise RayEngineError(f"{what} did not finish within {timeout_s:.0f} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def connect(address: str, num_cpus: int | None = None, timeout_s: float = START_TIMEOUT_S) -> bool:
    """Reach Ray; returns True when this call started or connected it (so ``close`` must shut it down).

    ``"local"`` starts a fresh instance on this machine bound to 127.0.0.1 with ``num_cpus`` CPUs (all of
    them when None); ``"auto"`` or ``ray://head:10001`` connect to a running cluster. When this process is
    already connected (a test, a notebook), that connection is used and left alone."""
    ray = _import_ray()

    if ray.is_initialized():
        return False
    quiet = {"logging_level": logging.WARNING, "log_to_driver": False, "configure_logging": True}
    if address == "local":
        kwargs = {"address": "local", "num_cpus": num_cpus, "include_dashboard": False}
        kwargs["_node_ip_address"] = "127.0.0.1"
    else:
        kwargs = {"address": address}
    attempts = CLIENT_ATTEMPTS if address.startswith("ray://") else 1
    for attempt in range(1, attempts + 1):
        try:
            with _deadline(timeout_s, f"starting or reaching Ray (address {address!r})"):
                ray.init(**kwargs, **quiet)
            break
        except ConnectionError as e:
            if SESSION_START_FAILED not in str(e):  # nothing listening, refused, a wrong token: no retry
                raise
            if attempt == attempts:
                raise RayEngineError(f"the Ray Client at {address} failed {attempts} times: {e}") from e
            log.warning("Ray Client session at %s failed to start (%s); trying again", address, e)
            if ray.is_initialized():
                ray.shutdown()
            time.sleep(CLIENT_RETRY_PAUSE_S)
    log.info("Ray reached at %r: %s CPUs", address, ray.cluster_resources().get("CPU", 0))
    return True


# -- shipping the pipeline ---------------------------------------------------------------------------------
def model_files(source: PipelineSource) -> dict[str, Path]:
    """What an actor needs to load ``source``: the fitted pipeline folder and the ONNX models its
    configuration uses, by their path relative to a models dir."""
    from app.engine.registry import files_for

    register_added_models(source.models_dir)  # an added model's files ship like a built-in's
    config = get_config(source.config)
    files = {name: source.models_dir / name for name in files_for(config)}
    if not source.directory.is_dir():
        raise RayEngineError(f"no fitted pipeline in {source.directory}: run `geoloc fit` first")
    for f in sorted(source.directory.iterdir()):
        if f.is_file():
            files[f"pipelines/{source.config}/{f.name}"] = f
    missing = [str(p) for p in files.values() if not p.is_file()]
    if missing:
        raise RayEngineError(f"model files are missing: {', '.join(missing)} (run `geoloc models build`)")
    return files


@dataclass(frozen=True)
class PipelinePackage:
    """A pipeline's files as bytes, put in the object store once per job (no shared filesystem needed)."""

    config: str
    files: dict[str, bytes]

    @classmethod
    def of(cls, source: PipelineSource) -> PipelinePackage:
        return cls(source.config, {name: p.read_bytes() for name, p in model_files(source).items()})

    def unpack(self, into: Path) -> PipelineSource:
        for name, data in self.files.items():
            path = into / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        return PipelineSource(into, into / "pipelines" / self.config, self.config)


# -- the actor ---------------------------------------------------------------------------------------------
class EncoderActor:
    """One pool member: loads the pipeline once, then encodes batches with the local path's functions."""

    def __init__(self, pipeline: PipelineSource | PipelinePackage, limits: ImageLimits, threads: int = 1):
        import cv2

        from app.engine.models.ort import set_session_threads

        # before any session is built: onnxruntime and OpenCV use exactly the CPUs this actor holds
        set_session_threads(threads)
        cv2.setNumThreads(threads)
        self.tmp: Path | None = None
        if isinstance(pipeline, PipelinePackage):
            self.tmp = Path(tempfile.mkdtemp(prefix="geoloc-ray-"))
            pipeline = pipeline.unpack(self.tmp)
        self.pipeline = pipeline.load()
        self.limits = limits

    def pid(self) -> int:
        return os.getpid()

    def cpu_seconds(self) -> float:
        """CPU time this actor's process has used (all its threads): what a batch costs, whatever the load."""
        return time.process_time()

    def encode(self, items: list[EncodeItem]) -> list[Encoded]:
        return [encode_item(self.pipeline, self.limits, i) for i in items]

    def cleanup(self) -> None:
        if self.tmp is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.tmp = None


# -- the engine --------------------------------------------------------------------------------------------
class RayEngine:
    """``EncodeEngine`` over a pool of ``workers`` encoder actors (1 CPU each) on a Ray cluster."""

    def __init__(
        self,
        source: PipelineSource,
        limits: ImageLimits,
        address: str = "local",
        workers: int | None = None,
        shared_fs: bool = False,
        batch_size: int = 8,
        start_timeout_s: float = START_TIMEOUT_S,
        batch_timeout_s: float = BATCH_TIMEOUT_S,
        max_restarts: int = 3,
        max_task_retries: int = 3,
    ):
        """``workers``: actors in the pool (None or 0: one per CPU of the cluster). ``shared_fs``: the actors
        read the models and the images from the paths themselves instead of receiving them."""
        ray = _import_ray()

        if batch_size < 1:
            raise ValueError("batch_size must be at least 1")
        if workers is not None and workers < 0:
            raise ValueError("workers must be a positive number of actors (0 or None: one per CPU)")
        self.shared_fs = shared_fs
        self.batch_size = batch_size
        self.batch_timeout_s = batch_timeout_s
        self._owned = connect(address, workers or None, start_timeout_s)
        self._closed = False
        try:
            cpus = int(ray.cluster_resources().get("CPU", 0))
            self.workers = workers or max(1, cpus)
            if self.workers > cpus:
                log.warning(
                    "%d encoder actors asked, the cluster has %d CPUs: some may never start", self.workers, cpus
                )
            # held for the engine's life: a restarted actor is built again from the same object
            self._payload = source if shared_fs else ray.put(PipelinePackage.of(source))
            payload = self._payload
            actor_cls = ray.remote(EncoderActor).options(
                num_cpus=1, max_restarts=max_restarts, max_task_retries=max_task_retries
            )
            self.actors = [actor_cls.remote(payload, limits, 1) for _ in range(self.workers)]
            self._pids = self._get([a.pid.remote() for a in self.actors], start_timeout_s, "the encoder pool to start")
            log.info("%d encoder actors ready (pids %s)", self.workers, self._pids)
        except BaseException:
            self.close()
            raise

    def _get(self, refs: list, timeout_s: float, what: str) -> list:
        import ray
        from ray.exceptions import GetTimeoutError

        try:
            return ray.get(refs, timeout=timeout_s)
        except GetTimeoutError:
            cpus = ray.cluster_resources().get("CPU", 0)
            raise RayEngineError(
                f"timed out after {timeout_s:.0f} s waiting for {what} ({self.workers} actors of 1 CPU, "
                f"the cluster has {cpus:.0f} CPUs)"
            ) from None

    def actor_pids(self) -> list[int]:
        """The encoder processes now (after restarts, new ones): for monitoring and the fault tests."""
        return self._get([a.pid.remote() for a in self.actors], self.batch_timeout_s, "the actors' pids")

    def cpu_seconds(self) -> float:
        """CPU time used by the pool's processes so far (for benchmarks: independent of the machine's load)."""
        return float(sum(self._get([a.cpu_seconds.remote() for a in self.actors], self.batch_timeout_s, "CPU times")))

    def run(self, items: Iterable[EncodeItem]) -> Iterator[Encoded]:
        """Results in completion order, as they come back; at most ``2 x workers`` batches in flight."""
        import ray
        from ray.exceptions import RayError

        if self._closed:
            raise RayEngineError("the engine is closed")
        it = iter(items)
        in_flight: dict[object, tuple[int, int]] = {}  # ref -> (actor index, items)
        load = [0] * len(self.actors)
        exhausted = False
        try:
            while True:
                while not exhausted and len(in_flight) < 2 * len(self.actors):
                    chunk = list(islice(it, self.batch_size))
                    if not chunk:
                        exhausted = True
                        break
                    batch: list[EncodeItem] = []
                    for item in chunk:
                        got = item if self.shared_fs else read_item(item)
                        if isinstance(got, Encoded):
                            yield got  # answered by the driver: nothing to encode
                        else:
                            batch.append(got)
                    if batch:
                        a = min(range(len(load)), key=load.__getitem__)
                        in_flight[self.actors[a].encode.remote(batch)] = (a, len(batch))
                        load[a] += 1
                if not in_flight:
                    return
                t0 = time.monotonic()
                ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=self.batch_timeout_s)
                if not ready:
                    raise RayEngineError(
                        f"no batch finished within {self.batch_timeout_s:.0f} s ({len(in_flight)} in flight); "
                        "the rows not completed stay pending"
                    )
                a, n = in_flight.pop(ready[0])
                load[a] -= 1
                try:
                    results = ray.get(ready[0], timeout=max(1.0, self.batch_timeout_s - (time.monotonic() - t0)))
                except RayError as e:
                    raise RayEngineError(
                        f"a batch of {n} images failed after its retries ({type(e).__name__}: {e}); the rows not "
                        "completed stay pending"
                    ) from e
                yield from results
        finally:
            for ref in in_flight:  # an abandoned run (error, caller stopped) leaves nothing queued
                try:
                    ray.cancel(ref)
                except (RayError, TypeError, ValueError) as e:  # already finished, or not cancellable
                    log.debug("batch not cancelled: %s", e)

    def close(self) -> None:
        """Stop the pool (removing the actors' unpacked models) and shut down Ray if this engine started it."""
        import ray

        if self._closed:
            return
        self._closed = True
        actors = getattr(self, "actors", [])
        if actors and ray.is_initialized():
            # a pool that never started has actors that will not answer: do not wait long for them
            wait_s = 10 if getattr(self, "_pids", None) else 2
            ray.wait([a.cleanup.remote() for a in actors], num_returns=len(actors), timeout=wait_s)
            for a in actors:
                ray.kill(a, no_restart=True)
        if self._owned and ray.is_initialized():
            ray.shutdown()

    def __enter__(self) -> RayEngine:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
