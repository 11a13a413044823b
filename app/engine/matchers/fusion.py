"""How verification re-orders candidates: the fused score (the global score plus a saturating inlier bonus),
never raw inlier counts."""

from __future__ import annotations

import numpy as np

#: The fused score's inlier bonus: inliers up to ``FUSION_FLOOR`` count for nothing (on penn, wrong pairs'
#: chosen-model inliers have median 12 and p99 20: MAGSAC finds a dozen F "inliers" among any matches),
#: then the bonus rises towards ``FUSION_WEIGHT``, reached at a few times ``FUSION_SCALE`` inliers above
#: the floor. A fixed choice (floor at that p99); docs/results.md compares it with leave-one-fold-out ones.
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
    than the global score (the fused score does better; docs/results.md) because repetitive facades and
    chance give wrong candidates inliers too; the global score keeps its say, and a few dozen inliers are
    worth almost as much as hundreds, so one huge but wrong match cannot dominate. Why a floor: chance
    inliers would otherwise reshuffle unrelated candidates. Unverified pairs (0 inliers) keep their global
    score, so verification never pushes a candidate below where retrieval put it relative to other
    unverified ones."""
    return float(global_score + weight * (1.0 - np.exp(-max(inliers - floor, 0) / scale)))
