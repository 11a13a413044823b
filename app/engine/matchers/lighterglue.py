"""The ``xfeat-lighterglue`` matcher: XFeat keypoints matched by LighterGlue (``app.engine.models.lighterglue``),
then the H-or-F geometry.

Why a learned matcher: counting inliers of nearest-neighbour matches cannot tell lookalike buildings apart;
LightGlue decides matchability from both images' keypoints in context, so wrong pairs get few,
unconfident matches. Per pair it reports what a confidence rule can use (``Verification``): tentative
matches, inliers of the chosen geometry, and the mean confidence of the matches.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from app.engine.matchers.base import Matcher, Verification
from app.engine.matchers.geometry import fit_geometry
from app.engine.models.lighterglue import (
    BATCH,
    LONG_SIDE,
    MATCH_THRESHOLD,
    MAX_KEYPOINTS,
    MODEL_FILENAME,
    KeypointFeatures,
    LighterGlue,
)
from app.engine.models.xfeat import MODEL_FILENAME as XFEAT_FILENAME
from app.engine.models.xfeat import XFeat
from app.engine.registry import Kind, Plugin, register


class LighterGlueMatcher(Matcher[KeypointFeatures]):
    """The ``xfeat-lighterglue`` matcher: XFeat keypoints (``LONG_SIDE``, ``MAX_KEYPOINTS``), LighterGlue
    matches, then the H-or-F geometry (``app.engine.matchers.geometry.fit_geometry``). One instance serves every
    request (onnxruntime sessions are thread-safe)."""

    def __init__(
        self,
        models_dir: Path,
        long_side: int = LONG_SIDE,
        max_keypoints: int = MAX_KEYPOINTS,
        threshold: float = MATCH_THRESHOLD,
        batch: int = BATCH,
    ):
        self.xfeat = XFeat(Path(models_dir) / XFEAT_FILENAME)
        self.glue = LighterGlue(Path(models_dir) / MODEL_FILENAME)
        self.long_side, self.max_keypoints = long_side, max_keypoints
        self.threshold, self.batch = threshold, batch

    def load(self) -> None:
        self.xfeat.load()
        self.glue.load()

    def features(self, rgb: np.ndarray) -> KeypointFeatures:
        h, w = rgb.shape[:2]
        s = self.long_side / max(h, w)
        if s < 1:
            rgb = cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
            h, w = rgb.shape[:2]
        out = self.xfeat.detect_and_compute(rgb, self.max_keypoints)
        return KeypointFeatures(out.keypoints, out.descriptors, (w, h))

    def match_many(self, query: KeypointFeatures, candidates: Sequence[KeypointFeatures]) -> list[Verification]:
        """One ``Verification`` per candidate: LighterGlue matches (``batch`` pairs per network run),
        then the geometry; ``mean_confidence`` is the matches' mean probability (0 without matches)."""
        results = []
        for c, m in zip(candidates, self.glue.match_many(query, candidates, self.threshold, self.batch), strict=True):
            v = fit_geometry(query.xy[m.pairs[:, 0]], c.xy[m.pairs[:, 1]])
            mean = float(m.confidence.mean()) if len(m.confidence) else 0.0
            results.append(replace(v, mean_confidence=round(mean, 4)))
        return results

    def match(self, query: KeypointFeatures, candidate: KeypointFeatures) -> Verification:
        return self.match_many(query, [candidate])[0]


register(Plugin(Kind.MATCHER, "xfeat-lighterglue", LighterGlueMatcher, (XFEAT_FILENAME, MODEL_FILENAME)))
