"""The ``sift-mnn`` matcher, the default: RootSIFT, mutual nearest neighbours with the ratio test, then the
H-or-F geometry (``geometry.fit_geometry``).

Why RootSIFT: it is the most distinctive descriptor the pipelines have, and what was measured
(docs/results.md, "Verification that works"). Positions are in pixels, as RANSAC thresholds are.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine.local_features import RootSift
from app.engine.matchers.base import Matcher, Verification
from app.engine.matchers.geometry import verify
from app.engine.registry import Kind, Plugin, register

#: Verification resolution and keypoint cap: 800 px and 1,500 RootSIFT keypoints. Reference features are
#: recomputed from the stored image (a decode and a RootSIFT each); all 1,500 would take 193 KB stored, three
#: times the 64 KB a reference may take (docs/results.md, "Verification that works").
VERIFY_LONG_SIDE = 800
VERIFY_MAX_KEYPOINTS = 1500
_extractor = RootSift(max_keypoints=VERIFY_MAX_KEYPOINTS, long_side=VERIFY_LONG_SIDE)


@dataclass(frozen=True)
class PixelFeatures:
    """Local features with positions in pixels of the image as the extractor saw it (long side at most
    ``VERIFY_LONG_SIDE``): RANSAC thresholds are in pixels, so positions must be too."""

    xy: np.ndarray  # (N, 2) float32 pixels
    descriptors: np.ndarray  # (N, D) float32

    def __len__(self) -> int:
        return len(self.xy)


def features_for_verification(rgb: np.ndarray) -> PixelFeatures:
    """RootSIFT of an RGB image, positions in pixels of the image resized to ``VERIFY_LONG_SIDE``."""
    f = _extractor(rgb)
    h, w = rgb.shape[:2]
    s = VERIFY_LONG_SIDE / max(h, w)
    if s < 1:  # the extractor's own resize (local_features._gray_at)
        w, h = round(w * s), round(h * s)
    return PixelFeatures(f.xy * np.array([w, h], np.float32), f.descriptors)


def verify_features(query: PixelFeatures, ref: PixelFeatures) -> Verification:
    """``geometry.verify`` with the settings the core uses for RootSIFT (mutual NN, ratio 0.9, 3 px, h_share 0.8)."""
    return verify(query.xy, query.descriptors, ref.xy, ref.descriptors)


class SiftMnnMatcher(Matcher[PixelFeatures]):
    """The default matcher (registry name ``sift-mnn``): RootSIFT at ``VERIFY_LONG_SIDE``, mutual nearest
    neighbours with the ratio test, then the H-or-F geometry. Stateless, so one instance serves every
    request."""

    def features(self, rgb: np.ndarray) -> PixelFeatures:
        return features_for_verification(rgb)

    def match(self, query: PixelFeatures, candidate: PixelFeatures) -> Verification:
        return verify_features(query, candidate)


def _sift_mnn(models_dir: Path | None) -> SiftMnnMatcher:
    return SiftMnnMatcher()


register(Plugin(Kind.MATCHER, "sift-mnn", _sift_mnn))
