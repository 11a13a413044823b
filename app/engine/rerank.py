"""Geometric verification of the top candidates (the optional, costly re-rank of METHOD.md).

Why: a global descriptor says "looks alike"; matching local features and fitting epipolar geometry with
RANSAC says "is the same 3D scene". Candidates are re-ordered by the number of inliers (score breaks ties).
Features are RootSIFT whatever the pipeline: verification wants the most distinctive descriptor.
"""

from __future__ import annotations

from dataclasses import dataclass

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


# -- verification as pure functions (numpy in, numbers out), for any local feature -----------------------
#
# Why separate from the RootSIFT helpers above: the application core that calls verification is being
# rewritten; these functions take descriptors and pixel positions of any extractor (RootSIFT, XFeat) and
# return plain numbers, so wiring them in is one call per candidate.

#: Fewer tentative matches than this and no model is fitted: RANSAC on a handful of matches finds a
#: "geometry" in noise (8 are the minimum for F, 4 for H), so the pair counts as unverified.
MIN_MATCHES_TO_FIT = 15


@dataclass(frozen=True)
class Verification:
    """The outcome for one (query, candidate) pair."""

    n_matches: int  # tentative matches (mutual NN passing the ratio or cosine test)
    inliers: int  # inliers of the chosen model; 0 when unverified
    model: str | None  # "H" (homography), "F" (fundamental matrix) or None (not fitted / failed)

    @property
    def verified(self) -> bool:
        return self.model is not None


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
    model), else F (a 3D scene seen from two places). Degenerate sets (collinear, repeated points) make
    OpenCV raise: the pair is then unverified, never an error."""
    n = len(p1)
    if n < min_matches:
        return Verification(n, 0, None)
    a, b = np.asarray(p1, np.float64), np.asarray(p2, np.float64)
    try:
        _, mask_h = cv2.findHomography(a, b, cv2.USAC_MAGSAC, threshold_px, maxIters=2000, confidence=0.999)
        _, mask_f = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, threshold_px, 0.999, 2000)
    except cv2.error:
        return Verification(n, 0, None)
    in_h = int(mask_h.sum()) if mask_h is not None else 0
    in_f = int(mask_f.sum()) if mask_f is not None else 0
    in_f = max(in_f, in_h)  # F always has at least H's inliers (a MAGSAC run may miss a few)
    if in_f == 0:
        return Verification(n, 0, None)
    if in_h >= h_share * in_f:
        return Verification(n, in_h, "H")
    return Verification(n, in_f, "F")


def verify(
    xy1_px: np.ndarray,
    d1: np.ndarray,
    xy2_px: np.ndarray,
    d2: np.ndarray,
    ratio: float | None = 0.9,
    min_cos: float | None = None,
    threshold_px: float = 3.0,
) -> Verification:
    """Match two images' features and fit their geometry: positions in pixels of each image."""
    m = mutual_matches(d1, d2, ratio, min_cos)
    return fit_geometry(np.asarray(xy1_px)[m[:, 0]], np.asarray(xy2_px)[m[:, 1]], threshold_px)


def fused_score(global_score: float, inliers: int, weight: float = 0.5, scale: float = 30.0) -> float:
    """Re-ranking score: the global similarity plus a saturating bonus for inliers,
    ``global_score + weight * (1 - exp(-inliers / scale))``.

    Why not raw inlier counts: on penn, raw F inlier counts separated right from wrong candidates poorly
    (AUC 0.72 RootSIFT, 0.65 XFeat) because repetitive facades give wrong candidates inliers too; the
    global score keeps its say, and a few dozen inliers are worth almost as much as hundreds, so one huge
    but wrong match cannot dominate. Unverified pairs (0 inliers) keep their global score, so verification
    never pushes a candidate below where retrieval put it relative to other unverified ones."""
    return float(global_score + weight * (1.0 - np.exp(-max(inliers, 0) / scale)))
