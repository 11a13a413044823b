"""Handcrafted local features: SIFT turned into RootSIFT, and ORB.

One small class per extractor with its default configuration (the hloc shape), registered by name here
(``app.engine.registry``) as the learned ones are in their modules. Both work on a copy of the image
resized to ``long_side`` and keep the strongest ``max_keypoints``: the cap bounds time and the VLAD cost,
and the strongest responses are the repeatable ones. Keypoint positions are returned as
fractions of the image size so that other stages (the CNN map) can sample at them whatever their size.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from app.engine.registry import Kind, Plugin, register


@dataclass(frozen=True)
class LocalFeatures:
    xy: np.ndarray  # (N, 2) float32, x/width and y/height in [0, 1]
    descriptors: np.ndarray  # (N, D) float32 (RootSIFT, or ORB bits as 0/1)
    raw: np.ndarray | None = None  # ORB: (N, 32) packed uint8, for Hamming matching

    def __len__(self) -> int:
        return len(self.xy)


class LocalExtractor(Protocol):
    """What a pipeline's local-feature extractor is: ``conf`` over its ``default_conf``, a descriptor length,
    and an image in, ``LocalFeatures`` out. Registered by name (``Kind.LOCAL_EXTRACTOR``); a configuration
    names it (``PipelineConfig.local``)."""

    default_conf: dict
    conf: dict

    @property
    def dim(self) -> int: ...

    def __call__(self, rgb: np.ndarray) -> LocalFeatures: ...


def _gray_at(rgb: np.ndarray, long_side: int) -> np.ndarray:
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    h, w = gray.shape
    s = long_side / max(h, w)
    if s < 1:
        gray = cv2.resize(gray, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    return gray


def _strongest(kps, desc, max_keypoints: int):
    if desc is None or len(kps) == 0:
        return [], None
    order = np.argsort([-k.response for k in kps], kind="stable")[:max_keypoints]
    return [kps[i] for i in order], desc[order]


def _positions(kps, shape) -> np.ndarray:
    h, w = shape
    if not kps:
        return np.zeros((0, 2), np.float32)
    pts = np.array([k.pt for k in kps], np.float32)
    return pts / np.array([w, h], np.float32)


class RootSift:
    """SIFT, then RootSIFT (L1-normalise, square root): Hellinger kernel instead of Euclid, a free gain."""

    default_conf = {"max_keypoints": 1000, "long_side": 640}

    def __init__(self, **conf):
        self.conf = {**self.default_conf, **conf}
        # Over-detect, then keep the strongest: SIFT's own nfeatures cap sorts the same way.
        self._sift = cv2.SIFT_create(nfeatures=self.conf["max_keypoints"])

    @property
    def dim(self) -> int:
        return 128

    def __call__(self, rgb: np.ndarray) -> LocalFeatures:
        gray = _gray_at(rgb, self.conf["long_side"])
        kps, desc = self._sift.detectAndCompute(gray, None)
        kps, desc = _strongest(kps, desc, self.conf["max_keypoints"])
        if desc is None:
            return LocalFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32))
        return LocalFeatures(_positions(kps, gray.shape), root_sift(desc))


def root_sift(desc: np.ndarray) -> np.ndarray:
    d = desc.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-7)
    return np.sqrt(d)


class Orb:
    """ORB: 256-bit binary descriptors, an order of magnitude cheaper than SIFT. For clustering each bit
    becomes a 0/1 coordinate (as in the thesis); the packed bits are kept for Hamming matching."""

    default_conf = {"max_keypoints": 1000, "long_side": 640}

    def __init__(self, **conf):
        self.conf = {**self.default_conf, **conf}
        self._orb = cv2.ORB_create(nfeatures=self.conf["max_keypoints"], fastThreshold=10)

    @property
    def dim(self) -> int:
        return 256

    def __call__(self, rgb: np.ndarray) -> LocalFeatures:
        gray = _gray_at(rgb, self.conf["long_side"])
        kps, desc = self._orb.detectAndCompute(gray, None)
        kps, desc = _strongest(kps, desc, self.conf["max_keypoints"])
        if desc is None:
            return LocalFeatures(
                np.zeros((0, 2), np.float32), np.zeros((0, 256), np.float32), np.zeros((0, 32), np.uint8)
            )
        bits = np.unpackbits(desc, axis=1).astype(np.float32)
        return LocalFeatures(_positions(kps, gray.shape), bits, desc)


def _sift(models_dir: Path | None, **conf) -> RootSift:
    return RootSift(**conf)


def _orb(models_dir: Path | None, **conf) -> Orb:
    return Orb(**conf)


register(Plugin(Kind.LOCAL_EXTRACTOR, "sift", _sift))
register(Plugin(Kind.LOCAL_EXTRACTOR, "orb", _orb))
