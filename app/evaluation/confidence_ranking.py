"""How well a confidence score ranks the answers: ours against published training-free
baselines, on the same queries.

Per query whose place the collection holds, the label is "the answer's first candidate lies within the
radius (25 m) of the truth", and each score ranks the queries by how sure it is of that:

- ``ours``: the answer's ``answer_p``, the calibrated ``p_within_25m`` of the estimate's group (what the
  confident threshold reads; 0 when the collection is uncalibrated or nothing was found);
- ``best_score``: the first candidate's global similarity alone (the retrieval score baseline);
- ``inliers``: the first candidate's verified inlier count alone (verified answers only);
- ``sue``: SUE (Zaffar, Nan, Kooij, "Estimation of Uncertainty in Visual Place Recognition", CVPR 2024):
  the spatial spread of the first ``SUE_TOP_K`` candidates' positions, each weighted by
  ``exp(-SUE_LAMBDA * d)`` with ``d`` the descriptor distance, here ``sqrt(2 - 2 s)`` from the cosine
  similarity ``s`` of L2-normalised codes; lower spread = more confident, so the score is minus the spread.

Each is measured by the area under its precision-recall curve (sklearn's ``average_precision_score``) and by
the precision of the quarter of the queries it is surest of (``precision_at_coverage``; ties at the cut
are counted by their mean label, as a random order among them would on average).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from app.engine.geo import haversine_m

#: SUE's settings as published: the top 10 candidates, weights exp(-350 x descriptor distance).
SUE_TOP_K = 10
SUE_LAMBDA = 350.0
#: The share of queries the precision is measured on (the surest first).
COVERAGE = 0.25
SCORES = ("ours", "best_score", "inliers", "sue")
#: A score for a query that has none (no candidates): below any real one.
_NONE = -1e12


def sue_spread(lat: Sequence[float], lon: Sequence[float], scores: Sequence[float]) -> float:
    """SUE's uncertainty of one answer: the weighted variance (m^2, east plus north) of the first
    ``SUE_TOP_K`` candidates' positions, weights ``exp(-SUE_LAMBDA * sqrt(2 - 2 s))`` normalised to sum to 1
    (shifted by the smallest distance first: the same weights, without underflow)."""
    lat = np.asarray(lat, float)[:SUE_TOP_K]
    lon = np.asarray(lon, float)[:SUE_TOP_K]
    s = np.clip(np.asarray(scores, float)[:SUE_TOP_K], -1.0, 1.0)
    if len(s) == 0:
        return math.inf
    d = np.sqrt(np.maximum(2.0 - 2.0 * s, 0.0))
    w = np.exp(-SUE_LAMBDA * (d - d.min()))
    w /= w.sum()
    mlat, mlon = float(w @ lat), float(w @ lon)
    north = haversine_m(lat, mlon, mlat, mlon) * np.sign(lat - mlat)
    east = haversine_m(mlat, lon, mlat, mlon) * np.sign(lon - mlon)
    return float(w @ (north**2 + east**2))


def query_record(answer, lat: float, lon: float, radius_m: float = 25.0) -> dict:
    """What the ranking needs of one located answer (``LocateAnswer``) of a query at (``lat``, ``lon``): the
    label and the four scores (``inliers`` None when the answer was not verified)."""
    cands = answer.candidates
    if not cands:
        return {"label": False, "ours": answer.answer_p or 0.0, "best_score": None, "inliers": None, "sue": None}
    first = cands[0]
    head = cands[:SUE_TOP_K]
    verified = bool(answer.verification)
    return {
        "label": bool(haversine_m(lat, lon, first.lat, first.lon) <= radius_m),
        "ours": float(answer.answer_p) if answer.answer_p is not None else 0.0,
        "best_score": float(max(c.score for c in cands)),
        "inliers": (first.inliers or 0) if verified else None,
        "sue": -sue_spread([c.lat for c in head], [c.lon for c in head], [c.score for c in head]),
    }


def precision_at_coverage(label: np.ndarray, score: np.ndarray, coverage: float = COVERAGE) -> float:
    """The share of right answers among the ``coverage`` share of queries with the highest scores; queries
    tied at the cut count by their mean label."""
    label, score = np.asarray(label, float), np.asarray(score, float)
    k = max(1, math.ceil(coverage * len(label)))
    cut = np.sort(score)[::-1][k - 1]
    above = score > cut
    tied = score == cut
    taken = label[above].sum() + (k - above.sum()) * label[tied].mean()
    return float(taken / k)


def rank_confidence(records: Sequence[dict], names: Sequence[str] = SCORES) -> dict:
    """AUC-PR and precision at ``COVERAGE`` of each score of ``names`` that every record has (``inliers``
    only for verified runs) over ``records`` (``query_record``'s)."""
    from sklearn.metrics import average_precision_score

    label = np.array([r["label"] for r in records], bool)
    out: dict = {"queries": len(records), "right": int(label.sum()), "coverage": COVERAGE, "scores": {}}
    if not len(records):
        return out
    for name in names:
        values = [r.get(name) for r in records]
        if name == "inliers" and all(v is None for v in values):
            continue  # an unverified run has no inliers
        score = np.array([_NONE if v is None else v for v in values], float)
        out["scores"][name] = {
            "auc_pr": float(average_precision_score(label, score)) if 0 < label.sum() < len(label) else None,
            "precision_at_coverage": precision_at_coverage(label, score),
        }
    return out


def ranking_lines(ranking: dict, title: str) -> list[str]:
    """The summary's lines for one ranking (``rank_confidence``'s)."""
    if not ranking or not ranking.get("scores"):
        return []
    cov = f"{ranking['coverage']:.0%}"
    out = [
        f"{title} ({ranking['queries']} queries, top-1 right for {ranking['right']}): "
        f"AUC-PR / precision at {cov} coverage"
    ]
    for name, v in ranking["scores"].items():
        auc = "n/a" if v["auc_pr"] is None else f"{v['auc_pr']:.3f}"
        out.append(f"  {name}: {auc} / {v['precision_at_coverage']:.3f}")
    return out
