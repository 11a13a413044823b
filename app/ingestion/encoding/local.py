"""The local encoding engine and the bulk loop: where the expensive step of ingestion (decode, local
features, CNN, aggregation) runs.

Why an engine boundary: encoding is the one cost that outgrows a machine, so the bulk paths (``geoloc
ingest``, re-indexing) hand their rows to an engine and complete what comes back in batches, while the
rest of the path (accept -> pending rows -> complete, one writer of the data dir) stays the core's. The
local engine is a thread pool in this process; the Ray engine (``app/ingestion/encoding/ray.py``) runs the same
``encode_item`` in actors of a Ray cluster. Both take ``EncodeItem`` values and yield ``Encoded`` results
in any order.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from itertools import islice
from typing import Protocol

from app.engine.imageio import ImageLimits
from app.engine.pipeline import Pipeline
from app.ingestion.completion import complete
from app.ingestion.encoding.items import Encoded, EncodeItem, encode_item
from app.usecases.service import GeolocService


class Encoder(Protocol):
    """What an engine needs of the service (``app.usecases.service.GeolocService``): the loaded pipeline and
    the image limits."""

    pipeline: Pipeline
    limits: ImageLimits


class EncodeEngine(Protocol):
    def run(self, items: Iterable[EncodeItem]) -> Iterator[Encoded]: ...

    def close(self) -> None: ...


class LocalEngine:
    """A thread pool in this process over one loaded pipeline (ONNX Runtime and OpenCV release the GIL)."""

    def __init__(self, pipeline: Pipeline, limits: ImageLimits, threads: int = 1):
        self.pipeline = pipeline
        self.limits = limits
        self.threads = max(1, threads)

    def _one(self, item: EncodeItem) -> Encoded:
        return encode_item(self.pipeline, self.limits, item)

    def run(self, items: Iterable[EncodeItem]) -> Iterator[Encoded]:
        if self.threads == 1:
            yield from map(self._one, items)
            return
        with ThreadPoolExecutor(max_workers=self.threads) as pool:
            # bounded look-ahead: at most 4 items per thread in flight, so memory stays flat on 10^6 rows
            it = iter(items)
            window = list(islice(it, 4 * self.threads))
            while window:
                yield from pool.map(self._one, window)
                window = list(islice(it, 4 * self.threads))

    def close(self) -> None:
        pass


def batched(items: Iterable, size: int) -> Iterator[list]:
    it = iter(items)
    while chunk := list(islice(it, size)):
        yield chunk


def encode_and_complete(
    service: GeolocService,
    items: Iterable[EncodeItem],
    engine: EncodeEngine,
    batch: int = 32,
    on_batch: Callable[[Sequence[Encoded]], None] | None = None,
    complete_batch: Callable[[GeolocService, Sequence[Encoded]], list[int]] = complete,
) -> int:
    """Run ``items`` through ``engine`` and complete the results in batches of ``batch`` (one transaction
    each, by this process: the one writer; ``complete_batch``: ``app.ingestion.completion.complete``, or a
    benchmark's timed call of it). Returns how many rows were completed."""
    done = 0
    for results in batched(engine.run(items), batch):
        done += len(complete_batch(service, results))
        if on_batch is not None:
            on_batch(results)
    return done


def make_engine(service: Encoder, ray: str | None = None, workers: int = 1, shared_fs: bool = False) -> EncodeEngine:
    """The engine a bulk command asked for: ``ray`` is None (local threads), ``"local"`` (start a Ray
    instance on this machine), ``"auto"`` or a cluster address such as ``ray://head:10001``."""
    if ray is None:
        return LocalEngine(service.pipeline, service.limits, workers)
    from app.ingestion.encoding.ray import RayEngine  # optional dependency: pip install geoloc[ray]

    source = service.pipeline.source
    if source is None:
        raise ValueError("the pipeline was not loaded from disk: a Ray worker cannot load it")
    return RayEngine(source, service.limits, address=ray, workers=workers, shared_fs=shared_fs)
