"""Batch feature extraction: decode and extract many photos on a thread pool, for every fit (``geoloc fit``,
the first start, ``geoloc refit``) and the evaluation.

Why one helper: each of them had its own thread pool, each deciding differently which decode limits apply,
what an unreadable photo does and how progress is shown, and what one learned (the sha256 the calibration
records, the EXIF position of a photo without one in its row) the others did not. Threads help because
OpenCV and onnxruntime release the GIL; extraction gives the same features with any number of them
(tests/test_fit_reproducible.py), so ``workers`` changes the time only.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from app.engine.errors import GeolocError
from app.engine.imageio import ImageLimits
from app.engine.pipeline import Features, Pipeline
from app.engine.progress import Progress
from app.storage.files import sha256_of

log = logging.getLogger("geoloc.extraction")


class Counter(Protocol):
    """What counts the photos done (``app.engine.progress.Progress`` is one; the first start's tells /ready)."""

    def update(self, n: int) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Extracted:
    """One photo's features, and what reading and decoding it told: the decode's time, reading the file
    included (the evaluation's per-stage times), its EXIF position and capture time (for a photo whose row
    has none) and the sha256 of its bytes (what ingesting it stores, and a calibration records)."""

    features: Features
    decode_ms: float
    gps: tuple[float, float] | None = None
    captured_at: str | None = None
    sha256: str = ""


def extract_batch(
    pipe: Pipeline,
    paths: Sequence[Path],
    *,
    limits: ImageLimits | None = None,
    workers: int = 1,
    progress: Counter | None = None,
    skip_unreadable: bool = False,
) -> list[Extracted | None]:
    """Read, decode (``Pipeline.decode`` under ``limits``: the pixels ingest and /locate see) and extract
    each of ``paths``, in order, on ``workers`` threads. ``progress`` counts the photos done (default: a bar
    on a terminal, else a line every tenth); it is closed at the end. ``skip_unreadable``: a photo that
    cannot be read or decoded is logged and comes back as None (a folder or a collection of the user's);
    otherwise its error is raised (a manifest names photos that must be there)."""

    def one(path: Path) -> Extracted | None:
        try:
            t0 = time.perf_counter()
            data = Path(path).read_bytes()
            img = pipe.decode(data, limits)
            decode_ms = (time.perf_counter() - t0) * 1000
        except (OSError, GeolocError) as e:
            if not skip_unreadable:
                raise
            log.warning("%s: not used (%s)", path, e)
            return None
        return Extracted(pipe.extract(img.rgb), decode_ms, img.gps, img.captured_at, sha256_of(data))

    progress = progress or Progress(len(paths), desc="extract", every=max(1, len(paths) // 10))
    out: list[Extracted | None] = []
    try:
        with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            for extracted in pool.map(one, paths):
                out.append(extracted)
                progress.update(1)
    finally:
        progress.close()
    return out
