"""Train an SVM bank from geotagged training photos against a fitted pipeline and its references.

Steps (METHOD.md, "SVM bank"): retrieve each training photo's top-n references with the unfiltered
pipeline; references within ``pos_radius_m`` are positives, references among the top-n beyond the
negative radius are confusers; label every local feature by its matches; train the bank; then choose the
decision threshold on a held-out part of the training photos (never on queries).

The negative radius: the thesis used about 225 m in a city. On a small area almost nothing is that far,
so the rule is: the median distance between references, at least 3 x the positive radius, at most 225 m.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from app.engine.geo import haversine_m
from app.engine.pipeline import Features, Pipeline
from app.engine.search import ReferenceIndex
from app.engine.svm_bank import BankParams, SvmBank, labels_from_scores, match_scores

KEEP_FRACTIONS = (0.3, 0.5, 0.7, 0.85)  # candidate operating points for the threshold


@dataclass
class Geotagged:
    features: Features
    lat: float
    lon: float
    group: str


def negative_radius(lats: np.ndarray, lons: np.ndarray, pos_radius_m: float, cap_m: float = 225.0) -> float:
    lats, lons = np.asarray(lats), np.asarray(lons)
    if len(lats) > 400:  # a sample is enough for a median
        pick = np.random.default_rng(0).choice(len(lats), 400, replace=False)
        lats, lons = lats[pick], lons[pick]
    d = haversine_m(lats[:, None], lons[:, None], lats[None, :], lons[None, :])
    med = float(np.median(d[np.triu_indices(len(lats), 1)])) if len(lats) > 1 else cap_m
    return float(min(cap_m, max(3 * pos_radius_m, med)))


def _retrieve(pipeline: Pipeline, index: ReferenceIndex, f: Features, top_n: int) -> np.ndarray:
    codes = pipeline.encode_features(f)
    _, ids = index.search(codes.float_, codes.binary, top_n)
    return ids


def build_training_set(
    pipeline: Pipeline,
    index: ReferenceIndex,
    refs: dict[int, Geotagged],
    train: list[Geotagged],
    params: BankParams,
    top_n: int = 20,
    pos_radius_m: float = 25.0,
    neg_radius_m: float | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    ids_all = np.array(list(refs), np.int64)
    lat = np.array([refs[i].lat for i in ids_all])
    lon = np.array([refs[i].lon for i in ids_all])
    neg_r = neg_radius_m or negative_radius(lat, lon, pos_radius_m)
    scored = []
    n_pos_refs = n_neg_refs = 0
    for t in tqdm(train, desc="svm labels", unit="img", leave=False):
        if t.features.n_local == 0:
            continue
        ids = _retrieve(pipeline, index, t.features, top_n)
        d = haversine_m(
            t.lat, t.lon, np.array([refs[int(i)].lat for i in ids]), np.array([refs[int(i)].lon for i in ids])
        )
        pos = [refs[int(i)].features.local for i, di in zip(ids, d, strict=True) if di <= pos_radius_m]
        neg = [refs[int(i)].features.local for i, di in zip(ids, d, strict=True) if di > neg_r]
        n_pos_refs += len(pos)
        n_neg_refs += len(neg)
        scored.append(
            (t.features.local, match_scores(t.features.local, pos), match_scores(t.features.local, neg), bool(pos))
        )
    all_neg = np.concatenate([s[2] for s in scored]) if scored else np.zeros(0)
    thr = float(np.quantile(all_neg[all_neg > -1], params.confuser_quantile)) if (all_neg > -1).any() else 1.0
    xs, ys = [], []
    for local, s_pos, s_neg, has_pos in scored:
        xs.append(local)
        ys.append(labels_from_scores(s_pos, s_neg, has_pos, params, thr))
    x = np.vstack(xs) if xs else np.zeros((0, 1), np.float32)
    y = np.concatenate(ys) if ys else np.zeros(0, np.int8)
    report = {
        "negative_radius_m": round(neg_r, 1),
        "positive_radius_m": pos_radius_m,
        "top_n": top_n,
        "training_photos": len(scored),
        "positive_references": n_pos_refs,
        "confuser_references": n_neg_refs,
        "labelled_positive": int((y > 0).sum()),
        "labelled_negative": int((y < 0).sum()),
        "unlabelled": int((y == 0).sum()),
        "confuser_threshold": round(thr, 4),
    }
    return x, y, report


def recall_at_1(
    pipeline: Pipeline,
    index: ReferenceIndex,
    refs: dict[int, Geotagged],
    queries: list[Geotagged],
    bank: SvmBank | None,
    radius_m: float,
) -> tuple[float, float]:
    hits1 = hits5 = 0
    for q in queries:
        keep = bank.keep(q.features.local) if bank is not None and q.features.n_local else None
        codes = pipeline.encode_features(q.features, keep)
        _, ids = index.search(codes.float_, codes.binary, 5)
        d = [haversine_m(q.lat, q.lon, refs[int(i)].lat, refs[int(i)].lon) for i in ids]
        hits1 += bool(d and d[0] <= radius_m)
        hits5 += any(x <= radius_m for x in d)
    n = max(len(queries), 1)
    return hits1 / n, hits5 / n


def fit_bank(
    pipeline: Pipeline,
    index: ReferenceIndex,
    refs: dict[int, Geotagged],
    train: list[Geotagged],
    params: BankParams,
    pos_radius_m: float = 25.0,
    holdout_fraction: float = 0.3,
    min_keep: int = 50,
) -> SvmBank:
    """Labels and SVMs from part of the training photos; threshold from the rest (split by group)."""
    started = time.time()
    groups = sorted({t.group for t in train})
    rng = np.random.default_rng(params.seed)
    rng.shuffle(groups)
    n_hold = max(1, round(len(groups) * holdout_fraction)) if len(groups) > 1 else 0
    held = set(groups[:n_hold])
    fit_part = [t for t in train if t.group not in held]
    hold_part = [t for t in train if t.group in held]
    x, y, report = build_training_set(pipeline, index, refs, fit_part, params, pos_radius_m=pos_radius_m)
    bank = SvmBank.train(x, y, params)
    bank.min_keep = min_keep
    # Threshold: the keep fraction that does best on the held-out training photos (R@1, then R@5, then
    # keeping more); "keep everything" is always a candidate, so the bank can only be switched off, not harm.
    decisions = np.concatenate(
        [bank.decision(t.features.local) for t in hold_part if t.features.n_local] or [np.zeros(1)]
    )
    candidates = [(1.0, -1e9)] + [(f, float(np.quantile(decisions, 1 - f))) for f in KEEP_FRACTIONS]
    trials = []
    for frac, thr in candidates:
        bank.threshold = thr
        r1, r5 = recall_at_1(pipeline, index, refs, hold_part, bank, pos_radius_m)
        trials.append({"keep_fraction": frac, "threshold": thr, "heldout_r1": r1, "heldout_r5": r5})
    best = max(trials, key=lambda t: (t["heldout_r1"], t["heldout_r5"], t["keep_fraction"]))
    bank.threshold = best["threshold"]
    bank.manifest.update(
        {
            "training": report,
            "heldout_photos": len(hold_part),
            "threshold_trials": [
                {k: (round(v, 4) if isinstance(v, float) and np.isfinite(v) else v) for k, v in t.items()}
                for t in trials
            ],
            "chosen_keep_fraction": best["keep_fraction"],
            "train_seconds": round(time.time() - started, 1),
        }
    )
    return bank
