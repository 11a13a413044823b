"""The matcher contract: features once per image, then each (query, candidate) pair matched and its
geometry fitted into one ``Verification``.

Why a base class: the locate path verifies every candidate of a query through ``match_many`` alone, so a
matcher that gains from seeing the candidates together (a learned one batches its network runs; matching
against features stored at ingestion reads them in one go) overrides it, and every other matcher inherits
the pair-by-pair loop, with a pair OpenCV refuses counted as unverified rather than failing the others.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

import cv2
import numpy as np

from app.engine.errors import GeolocError


@dataclass(frozen=True)
class Verification:
    """The outcome of verifying one (query, candidate) pair."""

    n_matches: int  # tentative matches (mutual NN passing the ratio or cosine test)
    inliers: int  # inliers of the chosen model; 0 when unverified
    model: str | None  # "H" (homography), "F" (fundamental matrix) or None (not fitted / failed)
    h_inliers: int = 0  # both fits' counts, so the H-or-F rule can be measured (bench/verification.py)
    f_inliers: int = 0
    error: str | None = None  # the pair could not be verified (OpenCV refused it): unverified, never an exception
    #: A learned matcher's mean match probability over the tentative matches (0 without matches); None
    #: for matchers that give no probability (``sift-mnn``).
    mean_confidence: float | None = None

    @property
    def verified(self) -> bool:
        return self.model is not None


#: A matcher's own per-image features (positions in pixels plus descriptors, in whatever form it needs).
F = TypeVar("F")


class Matcher(ABC, Generic[F]):
    """Verification of a query against its candidates. Registered by name (``app.engine.registry``); a
    configuration names it (``PipelineConfig.matcher``). Instances are shared by every request, so a
    matcher keeps no per-request state."""

    def load(self) -> None:
        """Load what the matcher runs (its networks), so a missing file shows at start-up; none by default."""

    @abstractmethod
    def features(self, rgb: np.ndarray) -> F:
        """One image's features for matching (the query's once per request, a candidate's once per image)."""

    @abstractmethod
    def match(self, query: F, candidate: F) -> Verification:
        """Match one pair and fit its geometry."""

    def match_many(self, query: F, candidates: Sequence[F]) -> list[Verification]:
        """One ``Verification`` per candidate, in order: what the locate path calls. The default matches pair
        by pair; a pair that raises (OpenCV refusing its sample, a feature the matcher cannot read) is
        unverified with ``error`` set, and the other pairs still count."""
        out = []
        for c in candidates:
            try:
                out.append(self.match(query, c))
            except (cv2.error, GeolocError) as e:
                out.append(Verification(0, 0, None, error=str(e).strip().splitlines()[-1][:200] or type(e).__name__))
        return out
