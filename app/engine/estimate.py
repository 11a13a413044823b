"""Fuse ranked candidates into one position with a confidence, or decline with a reason.

Why: most users want one answer first. The top-1 alone is brittle (one look-alike facade wins), while
several references agreeing on one spot is strong evidence. So: weight each candidate by a softmax of its
score, group candidates lying within ``cluster_radius_m`` of each other, take the heaviest group, and
report its weighted centre, its spread as the uncertainty radius, and its share of the total weight as
the confidence. A confidence below ``min_confidence`` marks it as not confident, with a reason.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.engine.geo import haversine_m

#: Radius = max(farthest fused candidate + MARGIN_M, RADIUS_FLOOR_M); see ``fuse_position``.
#: Chosen by ``bench/calibrate_answers.py --eval out/eval/hybrid.json --coverage 0.8`` (a probe kept in history:
#: ``git show 00671a8:bench/calibrate_answers.py``; the served default, with
#: its collection-trained SVM bank; 5 folds, penn-campus-gps): cross-validated, the truth lies within the stated
#: radius for about the share aimed at.
MARGIN_M = 40.0
RADIUS_FLOOR_M = 10.0


@dataclass(frozen=True)
class Estimate:
    lat: float | None  # the fused position, even when not confident (evaluation measures it)
    lon: float | None
    radius_m: float | None
    confidence: float
    reason: str | None = None  # why the estimate should not be trusted, or None when it is confident
    support: int = 0  # candidates in the winning cluster
    members: tuple[bool, ...] = ()  # per fused candidate: in the winning cluster
    #: The share of such answers whose truth lies within ``radius_m``, when the collection's calibration chose
    #: the radius (``app.engine.calibration.fit_radius``); None: the constant rule below, its rate not calibrated.
    radius_rate: float | None = None

    @property
    def confident(self) -> bool:
        return self.reason is None


def fuse_position(
    lats: np.ndarray,
    lons: np.ndarray,
    scores: np.ndarray,
    cluster_radius_m: float = 25.0,
    temperature: float = 0.06,
    min_confidence: float = 0.5,
    top_n: int = 10,
    margin_m: float | None = None,
    min_radius_m: float | None = None,
) -> Estimate:
    """``scores`` are in [0, 1], best first. ``temperature`` sets how fast weight falls with score: at
    0.06 a candidate 0.06 below the best weighs 37 % as much. The defaults come from
    ``bench/calibrate_estimate.py --eval out/eval/hybrid.json`` (a probe kept in history at 00671a8; the
    5-fold penn-campus-gps evaluation of
    the default configuration, target 70 % within 25 m), cross-validated (chosen on four folds' queries,
    measured on the fifth), they meet that target. The previous defaults (0.005, 0.8), chosen on 16 training
    captures, were confident far more often and right far less often."""
    margin_m = MARGIN_M if margin_m is None else margin_m
    min_radius_m = RADIUS_FLOOR_M if min_radius_m is None else min_radius_m
    lats, lons, scores = (np.asarray(a, np.float64)[:top_n] for a in (lats, lons, scores))
    if len(scores) == 0:
        return Estimate(None, None, None, 0.0, "no candidates: the index is empty or the region holds none")
    w = np.exp((scores - scores.max()) / temperature)
    d = haversine_m(lats[:, None], lons[:, None], lats[None, :], lons[None, :])
    near = d <= cluster_radius_m
    mass = near @ w  # weight of the group centred on each candidate
    best = int(np.argmax(mass))
    members = near[best]
    wm = w[members]
    lat = float(np.sum(lats[members] * wm) / wm.sum())
    lon = float(np.sum(lons[members] * wm) / wm.sum())
    spread = haversine_m(lat, lon, lats[members], lons[members])
    # Never smaller than the farthest candidate fused into it, plus a margin chosen so the truth lies within
    # the radius for the share of confident answers the README states (bench/calibrate_answers.py).
    radius = float(max(np.max(spread) + margin_m, min_radius_m))
    # Share of the weight, discounted when only one candidate supports it (no independent agreement).
    confidence = float(mass[best] / w.sum())
    if members.sum() == 1 and len(scores) > 1:
        confidence *= 0.5
    confidence = float(np.clip(confidence, 0.0, 1.0))
    if confidence < min_confidence:
        return Estimate(
            lat,
            lon,
            radius,
            confidence,
            f"ambiguous: the best group holds {confidence:.0%} of the "
            "candidates' weight; candidates disagree on the place",
            int(members.sum()),
            tuple(bool(m) for m in members),
        )
    return Estimate(lat, lon, radius, confidence, None, int(members.sum()), tuple(bool(m) for m in members))
