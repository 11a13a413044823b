"""Geometric verification of the top candidates (the optional, costly re-rank of METHOD.md).

Why: a global descriptor says "looks alike"; matching local features and fitting epipolar geometry with
RANSAC says "is the same 3D scene". Candidates are re-ordered by the number of inliers (score breaks ties).
Features are RootSIFT whatever the pipeline: verification wants the most distinctive descriptor.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.engine.local_features import LocalFeatures, RootSift

_extractor = RootSift(max_keypoints=1500, long_side=800)
MIN_MATCHES = 8


def features_for_verification(rgb: np.ndarray) -> LocalFeatures:
    return _extractor(rgb)


def count_inliers(a: LocalFeatures, b: LocalFeatures, ratio: float = 0.8, threshold: float = 0.004) -> int:
    """Inliers of a fundamental matrix (USAC MAGSAC) fitted on ratio-test matches; 0 if too few matches.
    Positions are fractions of the image size, so ``threshold`` is a fraction too."""
    if len(a) < MIN_MATCHES or len(b) < MIN_MATCHES:
        return 0
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if len(good) < MIN_MATCHES:
        return 0
    p1 = a.xy[[m.queryIdx for m in good]].astype(np.float64)
    p2 = b.xy[[m.trainIdx for m in good]].astype(np.float64)
    _, mask = cv2.findFundamentalMat(p1, p2, cv2.USAC_MAGSAC, threshold, 0.999, 2000)
    return int(mask.sum()) if mask is not None else 0
