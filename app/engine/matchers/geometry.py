"""Tentative matches and the geometry every matcher ends with: mutual nearest neighbours (with the ratio or
cosine test), then a homography or a fundamental matrix fitted with RANSAC.

Why here, shared: a global descriptor says "looks alike"; a geometry that explains many matches says "is
the same scene", whatever found the matches (RootSIFT nearest neighbours, LighterGlue). The functions take
descriptors and pixel positions of any extractor and return plain numbers.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.engine.matchers.base import Verification

#: Fewer tentative matches than this and no model is fitted: RANSAC on a handful of matches finds a
#: "geometry" in noise (8 are the minimum for F, 4 for H), so the pair counts as unverified.
MIN_MATCHES_TO_FIT = 15


def mutual_matches(
    d1: np.ndarray, d2: np.ndarray, ratio: float | None = 0.9, min_cos: float | None = None
) -> np.ndarray:
    """(M, 2) index pairs (i in d1, j in d2) that are each other's nearest neighbour (L2) and pass
    Lowe's ratio test (nearest / second nearest < ``ratio``, on L2 distances) and/or, for unit
    descriptors, a cosine threshold ``min_cos`` (XFeat's matcher uses 0.82)."""
    if len(d1) == 0 or len(d2) == 0:
        return np.zeros((0, 2), np.int64)
    a, b = np.asarray(d1, np.float32), np.asarray(d2, np.float32)
    sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2 * a @ b.T
    dist = np.sqrt(np.maximum(sq, 0))
    nn12 = dist.argmin(axis=1)
    nn21 = dist.argmin(axis=0)
    idx = np.arange(len(a))
    keep = nn21[nn12] == idx
    best = dist[idx, nn12]
    if ratio is not None and len(b) > 1:
        second = np.partition(dist, 1, axis=1)[:, 1]
        keep &= best < ratio * np.maximum(second, 1e-12)
    if min_cos is not None:
        keep &= (a[idx] * b[nn12]).sum(1) > min_cos
    return np.stack([idx[keep], nn12[keep]], axis=1)


def fit_geometry(
    p1: np.ndarray,
    p2: np.ndarray,
    threshold_px: float = 3.0,
    h_share: float = 0.8,
    min_matches: int = MIN_MATCHES_TO_FIT,
) -> Verification:
    """Fit a homography and a fundamental matrix (USAC MAGSAC) to matched pixel positions (M, 2) each.

    The rule: F explains every pair H does (a plane is one of F's scenes), so its inlier count is always
    at least H's and raw counts would always pick F, whose extra freedom also fits wrong matches. We keep
    H when it explains at least ``h_share`` of F's inliers (a plane, or a rotation: H is the tighter
    model), else F (a 3D scene seen from two places). Some sample sets make OpenCV's USAC raise (seen on
    penn pairs with positions as image fractions): the other model's answer stands, and if both raise the
    pair is unverified (``error`` says why), never an exception."""
    n = len(p1)
    if n < min_matches:
        return Verification(n, 0, None)
    a, b = np.asarray(p1, np.float64), np.asarray(p2, np.float64)
    in_h, err_h = _inliers(
        lambda: cv2.findHomography(a, b, cv2.USAC_MAGSAC, threshold_px, maxIters=2000, confidence=0.999)
    )
    in_f, err_f = _inliers(lambda: cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, threshold_px, 0.999, 2000))
    if err_h and err_f:  # one refusal leaves the other model's answer; both: the pair is unverified
        return Verification(n, 0, None, error=err_f)
    in_f = max(in_f, in_h)  # F always has at least H's inliers (a MAGSAC run may miss a few)
    if in_f == 0:
        return Verification(n, 0, None, in_h, in_f)
    if in_h >= h_share * in_f:
        return Verification(n, in_h, "H", in_h, in_f)
    return Verification(n, in_f, "F", in_h, in_f)


def _inliers(fit) -> tuple[int, str | None]:
    """Inlier count of one OpenCV fit, or the reason OpenCV refused (USAC asserts on some sample sets)."""
    try:
        _, mask = fit()
    except cv2.error as e:
        return 0, str(e).strip().splitlines()[-1][:200]
    return (int(mask.sum()) if mask is not None else 0), None


def verify(
    xy1_px: np.ndarray,
    d1: np.ndarray,
    xy2_px: np.ndarray,
    d2: np.ndarray,
    ratio: float | None = 0.9,
    min_cos: float | None = None,
    threshold_px: float = 3.0,
    h_share: float = 0.8,
) -> Verification:
    """Match two images' features and fit their geometry: positions in pixels of each image."""
    m = mutual_matches(d1, d2, ratio, min_cos)
    return fit_geometry(np.asarray(xy1_px)[m[:, 0]], np.asarray(xy2_px)[m[:, 1]], threshold_px, h_share)
