"""Encode a query, search, and fuse: the one code path shared by the CLI, the evaluation and the service,
so the figures the evaluation prints are those of the code users run."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from app.engine.estimate import Estimate, fuse_position
from app.engine.pipeline import Features, Pipeline
from app.engine.search import ReferenceIndex

#: ids -> (lats, lons); references without a known position must not be in the index.
PositionLookup = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Candidate:
    reference_id: int
    lat: float
    lon: float
    score: float


@dataclass
class LocateResult:
    candidates: list[Candidate]
    estimate: Estimate
    mode: str
    features_extracted: int
    features_kept: int
    timings_ms: dict[str, float] = field(default_factory=dict)


class Locator:
    def __init__(
        self, pipeline: Pipeline, index: ReferenceIndex, positions: PositionLookup, cluster_radius_m: float = 25.0
    ):
        self.pipeline, self.index, self.positions = pipeline, index, positions
        self.cluster_radius_m = cluster_radius_m

    def locate_features(
        self,
        features: Features,
        top_k: int = 10,
        mode: str | None = None,
        allowed: np.ndarray | None = None,
        keep: np.ndarray | None = None,
    ) -> LocateResult:
        mode = self.index.check_mode(mode)
        if keep is None:
            keep = self.pipeline.select(features)
        codes = self.pipeline.encode_features(features, keep)
        t = codes.timings_ms
        t0 = time.perf_counter()
        scores, ids = self.index.search(codes.float_, codes.binary, top_k, mode, allowed)
        t["search"] = (time.perf_counter() - t0) * 1000
        t0 = time.perf_counter()
        lats, lons = self.positions(ids) if len(ids) else (np.zeros(0), np.zeros(0))
        estimate = fuse_position(lats, lons, scores, self.cluster_radius_m)
        t["estimate"] = (time.perf_counter() - t0) * 1000
        cands = [
            Candidate(int(i), float(la), float(lo), float(s))
            for i, la, lo, s in zip(ids, lats, lons, scores, strict=True)
        ]
        return LocateResult(cands, estimate, mode, codes.features_extracted, codes.features_kept, t)

    def locate_rgb(self, rgb: np.ndarray, **kwargs) -> LocateResult:
        return self.locate_features(self.pipeline.extract(rgb), **kwargs)
