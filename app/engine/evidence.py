"""The evidence a locate has for each of its first candidates, as one small feature vector, made in one place.

Why one place: the confidence rule and ``p_within_25m`` (``app.engine.calibration``) are fitted on these
vectors and applied to them, on the user's own collection (``app.usecases.fitting.calibrate_collection``), in the
evaluation, and in /locate; a second copy of "what the evidence is" would drift from the first. A new kind of
evidence (a learned matcher's match confidence) is one more named column here: the rule is fitted on whatever
names the calibration sample carried, and reads the same names back, so nothing else changes.

Per candidate, in the order the estimate fuses them (best first):

- global evidence: its score, its gap to the best score, log(1 + rank), the best score, the gap between the
  first two scores (a clear winner or a crowd of look-alikes);
- spatial agreement: how many of the other candidates lie within 25 m of it, and the share of the
  softmax weight of the candidates within 25 m of it (the estimate's rule, seen from each candidate);
- distinctiveness, which reads score differences only (a new photo's absolute score level moves with the
  collection and the fit): its lead over the best candidate of another place (over 100 m away), and the
  spread of the scores (best minus last);
- verification, when it ran (``VERIFIED_NAMES``): log(1 + inliers), the inlier ratio of its tentative
  matches, log(1 + tentative matches), and the matcher's mean match confidence where the matcher gives one
  (a learned matcher does; RootSIFT gives none and reads 0).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from app.engine.geo import haversine_m
from app.engine.matchers.base import Verification

#: The estimate's softmax temperature and group radius (``app.engine.estimate.fuse_position``'s defaults).
TEMPERATURE = 0.06
AGREE_RADIUS_M = 25.0

GLOBAL_NAMES = (
    "score",
    "gap_to_best",
    "log_rank",
    "best_score",
    "gap_1_2",
    "log_neighbours",
    "group_share",
    "lead_over_far",
    "gap_1_last",
)
#: A rival place: a candidate farther than this from the one scored (``lead_over_far``).
FAR_M = 100.0
VERIFIED_NAMES = ("log_inliers", "inlier_ratio", "log_matches", "match_confidence")


@dataclass(frozen=True)
class Evidence:
    """One row per candidate (``values[i]`` for the i-th fused candidate), one named column per feature."""

    names: tuple[str, ...]
    values: np.ndarray  # (n candidates, len(names)) float64

    def columns(self, names: Sequence[str]) -> np.ndarray:
        """The columns a calibration was fitted on, in its order; a missing one (verification did not run
        this time) reads 0, which is what an unverified pair looks like."""
        out = np.zeros((len(self.values), len(names)))
        for j, n in enumerate(names):
            if n in self.names:
                out[:, j] = self.values[:, self.names.index(n)]
        return out

    @property
    def verified(self) -> bool:
        return VERIFIED_NAMES[0] in self.names


def gather(
    lats: np.ndarray,
    lons: np.ndarray,
    scores: np.ndarray,
    verification: Mapping[int, Verification | None] | None = None,
    ids: Sequence[int] | None = None,
) -> Evidence:
    """The evidence of the fused candidates (``lats``, ``lons``, ``scores`` best first). ``verification``
    (reference id -> the matcher's outcome, or None where the pair could not be verified) adds the verified
    columns; ``ids`` says which candidate is which reference."""
    lats, lons, scores = (np.asarray(a, np.float64) for a in (lats, lons, scores))
    n = len(scores)
    if n == 0:
        names = GLOBAL_NAMES + (VERIFIED_NAMES if verification is not None else ())
        return Evidence(names, np.zeros((0, len(names))))
    best = float(scores.max())
    second = float(np.sort(scores)[-2]) if n > 1 else best - 1.0  # a lone candidate: no rival at all
    w = np.exp((scores - best) / TEMPERATURE)
    d = haversine_m(lats[:, None], lons[:, None], lats[None, :], lons[None, :])
    near = d <= AGREE_RADIUS_M
    # How far each candidate's score stands above the best candidate of another place (farther than FAR_M):
    # a place the collection holds stands out from its look-alikes elsewhere; with no rival among the
    # candidates, above the last one.
    rival = np.where(d > FAR_M, scores[None, :], -np.inf).max(axis=1)
    rival = np.where(np.isfinite(rival), rival, float(scores.min()))
    cols = [
        scores,
        scores - best,
        np.log1p(np.arange(n, dtype=np.float64)),
        np.full(n, best),
        np.full(n, best - second),
        np.log1p(near.sum(axis=1) - 1.0),
        (near @ w) / w.sum(),
        scores - rival,
        np.full(n, best - float(scores.min())),
    ]
    names = GLOBAL_NAMES
    if verification is not None:
        if ids is None or len(ids) != n:
            raise ValueError("verified evidence needs the candidates' reference ids")
        v = [verification.get(int(i)) for i in ids]
        inl = np.array([x.inliers if x else 0 for x in v], np.float64)
        matches = np.array([x.n_matches if x else 0 for x in v], np.float64)
        conf = np.array([(x.mean_confidence or 0.0) if x else 0.0 for x in v], np.float64)
        cols += [np.log1p(inl), inl / np.maximum(matches, 1.0), np.log1p(matches), conf]
        names = GLOBAL_NAMES + VERIFIED_NAMES
    return Evidence(names, np.column_stack(cols))
