"""A toy matcher plug-in, as a new matcher's module would be: its features, its matching, its registration and
its named configuration, and nothing else (``test_matcher_plugin`` imports it; no module of app/ names it).

It is real: ORB keypoints (positions in pixels), brute-force Hamming matches kept when mutual, then the H-or-F
geometry every matcher ends with. It defines ``match`` only, so the locate path verifies through the base
class's ``match_many``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from app.engine.configs import PipelineConfig, get_config, register_config
from app.engine.matchers.base import Matcher, Verification
from app.engine.matchers.geometry import fit_geometry
from app.engine.registry import Kind, Plugin, register

NAME = "toy-orb"
LONG_SIDE = 480


@dataclass(frozen=True)
class OrbFeatures:
    xy: np.ndarray  # (N, 2) float32 pixels of the image at LONG_SIDE
    descriptors: np.ndarray  # (N, 32) uint8, packed ORB bits


class ToyOrbMatcher(Matcher[OrbFeatures]):
    def __init__(self, max_keypoints: int = 800):
        self.max_keypoints = max_keypoints

    def features(self, rgb: np.ndarray) -> OrbFeatures:
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        s = LONG_SIDE / max(gray.shape)
        if s < 1:
            gray = cv2.resize(gray, (round(gray.shape[1] * s), round(gray.shape[0] * s)), interpolation=cv2.INTER_AREA)
        kps, desc = cv2.ORB_create(nfeatures=self.max_keypoints).detectAndCompute(gray, None)
        if desc is None:
            return OrbFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8))
        return OrbFeatures(np.array([k.pt for k in kps], np.float32), desc)

    def match(self, query: OrbFeatures, candidate: OrbFeatures) -> Verification:
        if len(query.xy) == 0 or len(candidate.xy) == 0:
            return Verification(0, 0, None)
        pairs = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(query.descriptors, candidate.descriptors)
        i = np.array([m.queryIdx for m in pairs], np.int64)
        j = np.array([m.trainIdx for m in pairs], np.int64)
        return fit_geometry(query.xy[i], candidate.xy[j])


def _toy(models_dir: Path | None) -> ToyOrbMatcher:
    return ToyOrbMatcher()


register(Plugin(Kind.MATCHER, NAME, _toy))
CONFIG = PipelineConfig(
    **{
        **get_config("sift-mbvlad").model_dump(),
        "name": "sift-mbvlad-toy-orb",
        "description": "sift-mbvlad verified by the toy ORB matcher (test plug-in)",
        "k": 8,
        "svm_bank": False,
        "matcher": NAME,
    }
)
register_config(CONFIG)
