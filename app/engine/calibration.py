"""Each candidate's probability of lying within 25 m of the photo, from what the ranking knows.

Why: raw scores are squeezed into a narrow band (0.56-0.65 on penn-campus-gps) and mean nothing on their
own; a person needs "how likely is this one right". A logistic regression on the candidate's score, its
gap to the best score, its rank, whether it belongs to the estimate's group and the estimate's confidence,
fitted and checked cross-validated over the evaluation folds (bench/calibrate_answers.py, which prints the
constants below, with its held-out Brier score and reliability table in docs/RESULTS.md). Fitted on the
default configuration; other configurations get the same mapping, which is less well calibrated for them.
"""

from __future__ import annotations

import numpy as np

from app.engine.estimate import Estimate

#: Order: score, score - best score, log(1 + rank), in the estimate's group, estimate confidence.
#: From ``bench/calibrate_answers.py --eval out/eval/hybrid.json`` (hybrid with its collection-trained SVM bank,
#: as served; 5 folds, 4,850 candidates): held-out Brier score 0.115 against 0.166 for a constant rate.
COEF = (1.9396, 0.7653, -0.1715, 1.6356, 4.1667)
INTERCEPT = -5.0784


def candidate_features(lats: np.ndarray, lons: np.ndarray, scores: np.ndarray, estimate: Estimate) -> np.ndarray:
    scores = np.asarray(scores, np.float64)
    n = len(scores)
    rank = np.arange(n, dtype=np.float64)
    members = np.zeros(n)
    m = np.asarray(estimate.members, bool)
    members[: len(m)] = m
    return np.column_stack(
        [scores, scores - (scores.max() if n else 0.0), np.log1p(rank), members, np.full(n, estimate.confidence)]
    )


def probability_within(features: np.ndarray) -> np.ndarray:
    z = features @ np.asarray(COEF) + INTERCEPT
    return 1.0 / (1.0 + np.exp(-z))


def candidate_probabilities(lats, lons, scores, estimate: Estimate) -> np.ndarray:
    return probability_within(candidate_features(np.asarray(lats), np.asarray(lons), scores, estimate))
