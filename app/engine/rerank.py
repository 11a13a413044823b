"""Geometric verification of the top candidates (the optional, costly re-rank of METHOD.md).

Why: a global descriptor says "looks alike"; matching local features and fitting a homography or an
epipolar geometry with RANSAC says "is the same scene". The functions here take descriptors and pixel
positions of any extractor and return plain numbers; ``features_for_verification`` makes RootSIFT ones
(the most distinctive descriptor the pipelines have, and what was measured: docs/RESULTS.md). Candidates
are re-ordered by ``fused_score`` (the global score plus a saturating inlier bonus), never by raw counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from app.engine.local_features import RootSift

#: Verification resolution and keypoint cap: 800 px and 1,500 RootSIFT keypoints. Reference features are
#: recomputed from the stored image (about 0.1 s per full photo); all 1,500 would take 193 KB stored, three
#: times the 64 KB a reference may take (docs/RESULTS.md, "Verification that works").
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


#: Fewer tentative matches than this and no model is fitted: RANSAC on a handful of matches finds a
#: "geometry" in noise (8 are the minimum for F, 4 for H), so the pair counts as unverified.
MIN_MATCHES_TO_FIT = 15


@dataclass(frozen=True)
class Verification:
    """The outcome for one (query, candidate) pair."""

    n_matches: int  # tentative matches (mutual NN passing the ratio or cosine test)
    inliers: int  # inliers of the chosen model; 0 when unverified
    model: str | None  # "H" (homography), "F" (fundamental matrix) or None (not fitted / failed)
    h_inliers: int = 0  # both fits' counts, so the H-or-F rule can be measured (bench/verification.py)
    f_inliers: int = 0
    error: str | None = None  # OpenCV refused the sample set (degenerate): unverified, never an exception
    #: A learned matcher's mean match probability over the tentative matches (0 without matches); None
    #: for matchers that give no probability (``sift-mnn``).
    mean_confidence: float | None = None

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


def verify_features(query: PixelFeatures, ref: PixelFeatures) -> Verification:
    """``verify`` with the settings the core uses for RootSIFT (mutual NN, ratio 0.9, 3 px, h_share 0.8)."""
    return verify(query.xy, query.descriptors, ref.xy, ref.descriptors)


class SiftMnnMatcher:
    """The default matcher (registry name ``sift-mnn``): RootSIFT at ``VERIFY_LONG_SIDE``, mutual nearest
    neighbours with the ratio test, then the H-or-F geometry. Stateless, so one instance serves every
    request."""

    def features(self, rgb: np.ndarray) -> PixelFeatures:
        return features_for_verification(rgb)

    def match(self, query: PixelFeatures, candidate: PixelFeatures) -> Verification:
        return verify_features(query, candidate)


#: The fused score's inlier bonus: inliers up to ``FUSION_FLOOR`` count for nothing (on penn, wrong pairs'
#: chosen-model inliers have median 12 and p99 20: MAGSAC finds a dozen F "inliers" among any matches),
#: then the bonus rises towards ``FUSION_WEIGHT``, reached at a few times ``FUSION_SCALE`` inliers above
#: the floor. A fixed choice (floor at that p99); docs/RESULTS.md compares it with leave-one-fold-out ones.
FUSION_WEIGHT = 0.5
FUSION_SCALE = 30.0
FUSION_FLOOR = 20


def fused_score(
    global_score: float,
    inliers: int,
    weight: float = FUSION_WEIGHT,
    scale: float = FUSION_SCALE,
    floor: int = FUSION_FLOOR,
) -> float:
    """Re-ranking score: the global similarity plus a saturating bonus for inliers above a noise floor,
    ``global_score + weight * (1 - exp(-max(inliers - floor, 0) / scale))``.

    Why not raw inlier counts: on penn, raw F inlier counts separate right from wrong candidates no better
    than the global score (AUC 0.678 against 0.691; the fused score 0.723) because repetitive facades and
    chance give wrong candidates inliers too; the global score keeps its say, and a few dozen inliers are
    worth almost as much as hundreds, so one huge but wrong match cannot dominate. Why a floor: chance
    inliers would otherwise reshuffle unrelated candidates. Unverified pairs (0 inliers) keep their global
    score, so verification never pushes a candidate below where retrieval put it relative to other
    unverified ones."""
    return float(global_score + weight * (1.0 - np.exp(-max(inliers - floor, 0) / scale)))
