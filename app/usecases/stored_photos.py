"""Stored local features made from photos at hand, each photo once: what the calibration of a configuration
with ``stored_features`` verifies its sampled references from (``app.usecases.fitting.calibrate_collection``),
and what the evaluation's folds verify from (``app.evaluation.evaluate``, from its on-disk cache).

Why not read the data dir's feature files: a fit (``geoloc fit``, the first start, the evaluation's folds)
has no data dir yet, only photos; and making each record here with the profile's extractor
(``Pipeline.stored_extractor``, the code the encode path stores) from the photo's decode gives the same record
ingestion stores. A photo that is located too (a held-out reference) gets its record and its query features
from one extraction (``StoredExtractor.record_and_query``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from app.engine.matchers.sift_mnn import PixelFeatures
from app.engine.stored_features import StoredFeatures
from app.engine.stored_profiles import StoredExtractor


class PhotoStoredFeatures:
    """Photos' stored records and query features by one profile, by reference id: given made already
    (``records``, ``queries``), else made from ``photo(id)`` (its decoded pixels, None when unreadable) on
    first use. A ``StoredFeaturesSource`` for ``locate_features``; ``query`` gives a photo's features for
    locating it. Records made here are kept (about 60 KB each, for the references one fit holds: bounded by
    its sample); query features are kept only when given (230 KB each), otherwise made when asked."""

    def __init__(
        self,
        extractor: StoredExtractor,
        photo: Callable[[int], np.ndarray | None] | None = None,
        records: Mapping[int, StoredFeatures] | None = None,
        queries: Mapping[int, PixelFeatures] | None = None,
    ):
        self.extractor = extractor
        self.photo = photo
        self.records: dict[int, StoredFeatures | None] = dict(records or {})
        self.queries: dict[int, PixelFeatures] = dict(queries or {})
        self.extractions = 0
        self.seconds = 0.0  # spent decoding and extracting here

    @property
    def profile(self) -> str:
        return self.extractor.profile.name

    def _make(self, ref_id: int) -> PixelFeatures | None:
        if self.photo is None:
            self.records.setdefault(ref_id, None)
            return None
        t0 = time.perf_counter()
        rgb = self.photo(ref_id)
        if rgb is None:
            self.records[ref_id] = None
            self.seconds += time.perf_counter() - t0
            return None
        record, query = self.extractor.record_and_query(rgb)
        self.records[ref_id] = record
        self.extractions += 1
        self.seconds += time.perf_counter() - t0
        return query

    def stored_features(self, ids: Sequence[int]) -> dict[int, StoredFeatures]:
        out = {}
        for i in (int(i) for i in ids):
            if i not in self.records:
                self._make(i)
            record = self.records[i]
            if record is not None:
                out[i] = record
        return out

    def query(self, ref_id: int) -> PixelFeatures | None:
        """The photo's query features (None when it cannot be read): given, else extracted now (its record
        kept from the same extraction)."""
        if ref_id in self.queries:
            return self.queries[ref_id]
        if ref_id in self.records and self.records[ref_id] is None:
            return None  # unreadable, tried already
        return self._make(ref_id)
