"""Stored local-features profiles: which extractor makes a reference's stored record (at ingestion) and the
query's features (once per request), and how the two are matched.

Why a named profile rather than loose fields: the stored files are only comparable with a query extracted
the same way, so one name fixes the extractor, its image size, its keypoint cap, the matching rules and the
fused score's noise floor together. The name is also the folder the files live in
(``app.storage.feature_files``), so a configuration that changes any of them never reads another's files.

The one profile was chosen by measurement on penn-photos-40 (docs/benchmarks.md, "Stored local features for
verification"): XFeat at 640 px (long side), 900 keypoints, 64-d descriptors stored as uint8 (59.8 KB a
reference), matched as XFeat's upstream matcher does (mutual nearest neighbours, cosine > 0.82, no ratio
test), then the H-or-F geometry; the adaptive stop at the fusion weight (0.5) never changes the first
candidate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from app.engine.errors import GeolocError
from app.engine.matchers.sift_mnn import PixelFeatures
from app.engine.stored_features import StoredFeatures, from_pixels
from app.engine.stored_verification import Settings


class UnknownProfile(GeolocError):
    pass


@dataclass(frozen=True)
class StoredProfile:
    """One way of making, storing and matching local features for verification."""

    name: str
    kind: str  # the descriptor kind of ``app.engine.stored_features.KINDS``
    long_side: int  # the image is scaled down to this long side (never up) before extraction
    max_keypoints: int
    settings: Settings = field(default_factory=Settings)
    #: ``verify_stored``'s adaptive stop; the fusion weight (0.5) never changes the first candidate.
    stop_margin: float | None = 0.5
    #: Inliers up to this count nothing in the fused score (``matchers.fusion.fused_score``'s ``floor``), and the
    #: adaptive stop reads the same score. The floor is the chance level of the candidates retrieval confuses,
    #: not of random pairs: XFeat pairs far apart have few inliers (their p90 was the old floor, 12), but the
    #: WRONG (beyond 25 m) candidates among the verified top 10 of penn-campus-gps's 5 folds have many more (a
    #: shared facade verifies from across a street); the floor is their p95. At the old floor verification lost
    #: R@1 against no verification; at this one it gains (``bench.fusion_replay``, then a 5-fold run;
    #: docs/results.md, "Verified confidence from stored features").
    fusion_floor: int = 48


PROFILES: dict[str, StoredProfile] = {
    p.name: p
    for p in [
        StoredProfile(
            name="xfeat-640-n900",
            kind="xfeat",
            long_side=640,
            max_keypoints=900,
            settings=Settings(ratio=None, min_cos=0.82),
        ),
    ]
}


def get_profile(name: str) -> StoredProfile:
    try:
        return PROFILES[name]
    except KeyError:
        raise UnknownProfile(f"unknown stored-features profile {name!r}; one of {', '.join(PROFILES)}") from None


class StoredExtractor:
    """A profile's extractor over the models dir: the reference's stored record at ingestion, the query's
    features at /locate, from the same decoded pixels and the same code, so the two always agree."""

    def __init__(self, profile: StoredProfile, models_dir: Path):
        if profile.kind != "xfeat":
            raise UnknownProfile(f"profile {profile.name}: no extractor for {profile.kind!r} descriptors")
        from app.engine.models.xfeat import MODEL_FILENAME, XFeat

        self.profile = profile
        self.model = XFeat(Path(models_dir) / MODEL_FILENAME)

    def load(self) -> None:
        self.model.load()

    def _extract(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
        """(pixel positions, unit descriptors, width, height) of the image the extractor saw."""
        h, w = rgb.shape[:2]
        s = self.profile.long_side / max(h, w)
        if s < 1:
            rgb = cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
            h, w = rgb.shape[:2]
        out = self.model.detect_and_compute(rgb, top_k=self.profile.max_keypoints)
        return out.keypoints, out.descriptors, w, h

    def record(self, rgb: np.ndarray) -> StoredFeatures:
        """A reference's features in the stored form (``app.engine.stored_features.encode`` writes it)."""
        xy, desc, w, h = self._extract(rgb)
        return from_pixels(xy, desc, w, h, self.profile.kind)

    def query(self, rgb: np.ndarray) -> PixelFeatures:
        """The query's features, unquantised (only the stored side is compacted)."""
        xy, desc, _, _ = self._extract(rgb)
        return PixelFeatures(np.asarray(xy, np.float32), np.asarray(desc, np.float32))

    def record_and_query(self, rgb: np.ndarray) -> tuple[StoredFeatures, PixelFeatures]:
        """``record`` and ``query`` of one photo from one extraction: a photo that is both a reference and
        located (the calibration's held-out references, the evaluation's rows) costs one extraction."""
        xy, desc, w, h = self._extract(rgb)
        query = PixelFeatures(np.asarray(xy, np.float32), np.asarray(desc, np.float32))
        return from_pixels(xy, desc, w, h, self.profile.kind), query
