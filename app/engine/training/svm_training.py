"""Train an SVM bank from geotagged training photos against a fitted pipeline and its references.

Steps (method.md, "SVM bank"): retrieve each training photo's top-n references with the unfiltered
pipeline; references within ``pos_radius_m`` are positives, references among the top-n beyond the
negative radius are confusers; label every local feature by its matches; train the bank; then choose the
decision threshold on a held-out part of the training photos (never on queries).

The negative radius: the thesis used about 225 m in a city. On a small area almost nothing is that far,
so the rule is: the median distance between references, at least 3 x the positive radius, at most 225 m.

Training from the collection itself (``fit_bank_from_collection``): a deployment rarely has geotagged
photos apart from its references, so the references play the training photos. Each sampled reference is
retrieved against all the others, but never learns from itself: references of its own capture group
(a photo and its crops) and its near-duplicates (within ``near_m`` metres AND a retrieval score of at
least ``near_score``: the same view re-uploaded or re-shot) are skipped, as if they were not in the
index; every other reference is a positive or a confuser by GPS exactly as for a training photo. The
manifest's ``train`` rows, when there are any, are added to the sampled references. The sample is capped
(``max_photos`` references, whole capture groups, seeded), so the cost is bounded whatever the size of
the collection: labelling is one retrieval and ``top_n`` feature matchings per training photo.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass

import numpy as np

from app.engine.errors import GeolocError
from app.engine.geo import haversine_m
from app.engine.index.references import ReferenceIndex
from app.engine.pipeline import Features, Pipeline
from app.engine.progress import tracked
from app.engine.svm_bank import BankParams, SvmBank, labels_from_scores, match_scores

KEEP_FRACTIONS = (0.3, 0.5, 0.7, 0.85)  # candidate operating points for the threshold
#: The collection rule's cap on training photos sampled from the references (cost: docs/results.md).
MAX_COLLECTION_PHOTOS = 600
#: The collection rule's operating points, chosen on its held-out references. "Keep all" is not among
#: them: the served bank always filters, and whether it should filter at all was decided by the five-fold
#: measurement in docs/results.md (R@1 close to no bank's), not by a hundred held-out references.
COLLECTION_KEEP_FRACTIONS: tuple[float, ...] | None = KEEP_FRACTIONS


class NothingToTrainOn(GeolocError):
    """The SVM bank got no training photo or no labelled feature."""


@dataclass
class Geotagged:
    features: Features
    lat: float
    lon: float
    group: str


@dataclass(frozen=True)
class Exclusion:
    """Which retrieved references a training photo must not learn from (nor be scored against): those of
    its own capture group, and its near-duplicates: within ``near_m`` metres AND scoring at least
    ``near_score`` against its unfiltered code (search scores lie in [0, 1]). Why both conditions: two
    captures a few metres apart are the best positives there are, unless they are the same picture."""

    near_m: float = 5.0
    near_score: float = 0.9
    depth: int = 10  # how many extra references to retrieve to make up for the excluded ones


def _positions(refs: dict[int, Geotagged], ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.array([refs[int(i)].lat for i in ids]), np.array([refs[int(i)].lon for i in ids])


class _Retriever:
    """Top-n references of a training photo, with its own group and near-duplicates left out."""

    def __init__(self, pipeline: Pipeline, index: ReferenceIndex, refs: dict[int, Geotagged], rule: Exclusion):
        self.pipeline, self.index, self.refs, self.rule = pipeline, index, refs, rule
        self._near: dict[int, set[int]] = {}

    def _search(self, t: Geotagged, keep: np.ndarray | None, k: int) -> tuple[np.ndarray, np.ndarray]:
        codes = self.pipeline.encode_features(t.features, keep)
        return self.index.search(codes.float_, codes.binary, min(k, self.index.size))

    def near_duplicates(self, t: Geotagged) -> set[int]:
        """Decided once per photo on its unfiltered code, so every keep fraction skips the same ones."""
        key = id(t)
        if key not in self._near:
            scores, ids = self._search(t, None, 1 + self.rule.depth)
            lat, lon = _positions(self.refs, ids)
            d = haversine_m(t.lat, t.lon, lat, lon)
            near = (d <= self.rule.near_m) & (scores >= self.rule.near_score)
            self._near[key] = {int(i) for i in ids[near]}
        return self._near[key]

    def __call__(self, t: Geotagged, n: int, keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(ids, distances in metres) of up to ``n`` allowed references, best first."""
        skip = self.near_duplicates(t)
        k = n + self.rule.depth
        while True:
            _, ids = self._search(t, keep, k)
            ok = np.array([int(i) not in skip and self.refs[int(i)].group != t.group for i in ids], bool)
            if ok.sum() >= n or k >= self.index.size:
                ids = ids[ok][:n] if len(ids) else ids
                lat, lon = _positions(self.refs, ids)
                return ids, haversine_m(t.lat, t.lon, lat, lon)
            k *= 2


def negative_radius(lats: np.ndarray, lons: np.ndarray, pos_radius_m: float, cap_m: float = 225.0) -> float:
    lats, lons = np.asarray(lats), np.asarray(lons)
    if len(lats) > 400:  # a sample is enough for a median
        pick = np.random.default_rng(0).choice(len(lats), 400, replace=False)
        lats, lons = lats[pick], lons[pick]
    d = haversine_m(lats[:, None], lons[:, None], lats[None, :], lons[None, :])
    med = float(np.median(d[np.triu_indices(len(lats), 1)])) if len(lats) > 1 else cap_m
    return float(min(cap_m, max(3 * pos_radius_m, med)))


def build_training_set(
    pipeline: Pipeline,
    index: ReferenceIndex,
    refs: dict[int, Geotagged],
    train: list[Geotagged],
    params: BankParams,
    top_n: int = 20,
    pos_radius_m: float = 25.0,
    neg_radius_m: float | None = None,
    rule: Exclusion | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    retrieve = _Retriever(pipeline, index, refs, rule or Exclusion())
    ids_all = np.array(list(refs), np.int64)
    lat = np.array([refs[i].lat for i in ids_all])
    lon = np.array([refs[i].lon for i in ids_all])
    neg_r = neg_radius_m or negative_radius(lat, lon, pos_radius_m)
    scored = []
    n_pos_refs = n_neg_refs = 0
    for t in tracked(train, len(train), "svm labels"):
        if t.features.n_local == 0:
            continue
        ids, d = retrieve(t, top_n)
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
    rule: Exclusion | None = None,
    retriever: _Retriever | None = None,
) -> tuple[float, float]:
    """R@1 and R@5 of held-out training photos, each retrieved with its own group and near-duplicates
    left out (a held-out reference must not find itself)."""
    retrieve = retriever or _Retriever(pipeline, index, refs, rule or Exclusion())
    hits1 = hits5 = 0
    for q in queries:
        keep = bank.keep(q.features.local) if bank is not None and q.features.n_local else None
        _, d = retrieve(q, 5, keep)
        hits1 += bool(len(d) and d[0] <= radius_m)
        hits5 += bool(np.any(d <= radius_m))
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
    rule: Exclusion | None = None,
    keep_fractions: tuple[float, ...] | None = None,
) -> SvmBank:
    """Labels and SVMs from part of the training photos; threshold from the rest (split by group).

    ``keep_fractions``: the operating points tried on the held-out photos (fraction of their features
    the threshold keeps); by default "keep all" and ``KEEP_FRACTIONS``. Pass one value to fix the rule."""
    rule = rule or Exclusion()
    started = time.time()
    groups = sorted({t.group for t in train})
    rng = np.random.default_rng(params.seed)
    rng.shuffle(groups)
    n_hold = max(1, round(len(groups) * holdout_fraction)) if len(groups) > 1 else 0
    held = set(groups[:n_hold])
    fit_part = [t for t in train if t.group not in held]
    hold_part = [t for t in train if t.group in held]
    if not fit_part:
        raise NothingToTrainOn("no training photos for the SVM bank: no train rows and no references to sample")
    x, y, report = build_training_set(pipeline, index, refs, fit_part, params, pos_radius_m=pos_radius_m, rule=rule)
    if not (y > 0).any() and not (y < 0).any():
        raise NothingToTrainOn(
            f"the SVM bank's {len(fit_part)} training photos gave no labelled feature: no reference within "
            f"{pos_radius_m} m nor beyond the negative radius among their top matches"
        )
    bank = SvmBank.train(x, y, params)
    bank.min_keep = min_keep
    # Threshold: the keep fraction that does best on the held-out training photos (R@1, then R@5, then
    # keeping more); "keep everything" is always a candidate, so the bank can only be switched off, not harm.
    decisions = np.concatenate(
        [bank.decision(t.features.local) for t in hold_part if t.features.n_local] or [np.zeros(1)]
    )
    fractions = (1.0, *KEEP_FRACTIONS) if keep_fractions is None else tuple(keep_fractions)
    candidates = [(f, -1e9 if f >= 1.0 else float(np.quantile(decisions, 1 - f))) for f in fractions]
    retriever = _Retriever(pipeline, index, refs, rule)
    trials = []
    for frac, thr in candidates:
        bank.threshold = thr
        r1, r5 = recall_at_1(pipeline, index, refs, hold_part, bank, pos_radius_m, retriever=retriever)
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
            "exclusion": asdict(rule),
            "train_seconds": round(time.time() - started, 1),
        }
    )
    return bank


def sample_references(refs: dict[int, Geotagged], max_photos: int, seed: int = 0) -> list[Geotagged]:
    """Up to ``max_photos`` references, whole capture groups drawn in a seeded order (a group's crops
    come with their photo), so a large collection costs what ``max_photos`` costs."""
    by_group: dict[str, list[int]] = {}
    for i in sorted(refs):
        by_group.setdefault(refs[i].group, []).append(i)
    groups = sorted(by_group)
    np.random.default_rng(seed).shuffle(groups)
    picked: list[Geotagged] = []
    for g in groups:
        if len(picked) + len(by_group[g]) > max_photos and picked:
            break
        picked += [refs[i] for i in by_group[g]]
    return picked


def fit_bank_from_collection(
    pipeline: Pipeline,
    index: ReferenceIndex,
    refs: dict[int, Geotagged],
    params: BankParams,
    train: list[Geotagged] | None = None,
    max_photos: int = MAX_COLLECTION_PHOTOS,
    pos_radius_m: float = 25.0,
    min_keep: int = 50,
    rule: Exclusion | None = None,
    keep_fractions: tuple[float, ...] | None = COLLECTION_KEEP_FRACTIONS,
) -> SvmBank:
    """The bank from the references themselves (plus ``train`` photos when there are any): the rule in
    this module's docstring. ``refs`` must be exactly what ``index`` holds (ids to positions and features);
    the same function serves ``geoloc fit`` on a manifest and a refit from a data dir's stored references."""
    started = time.time()
    sample = sample_references(refs, max_photos, params.seed)
    photos = sample + list(train or [])
    bank = fit_bank(
        pipeline,
        index,
        refs,
        photos,
        params,
        pos_radius_m=pos_radius_m,
        min_keep=min_keep,
        rule=rule,
        keep_fractions=keep_fractions,
    )
    bank.manifest["source"] = {
        "kind": "collection",
        "references": len(refs),
        "sampled_references": len(sample),
        "train_photos": len(train or []),
        "max_photos": max_photos,
    }
    bank.manifest["train_seconds"] = round(time.time() - started, 1)
    return bank


#: Where a bank learns: the references themselves (plus train photos), train photos only, or nowhere.
BANK_SOURCES = ("collection", "train", "none")


def index_of(pipeline: Pipeline, ids: np.ndarray, features: Iterable[Features]) -> ReferenceIndex:
    """An in-memory index of features encoded by ``pipeline``: what a bank is trained against, built the
    same way by `geoloc fit`, `geoloc refit` and the evaluation's folds."""
    codes = [pipeline.encode_features(f) for f in features]
    index = pipeline.new_index()
    index.add(
        np.asarray(ids, np.int64),
        np.stack([c.float_ for c in codes]) if pipeline.float_dim else None,
        np.stack([c.binary for c in codes]) if pipeline.bits else None,
    )
    return index


def fit_bank_from(
    source: str,
    pipeline: Pipeline,
    index: ReferenceIndex,
    refs: dict[int, Geotagged],
    train: list[Geotagged],
    params: BankParams,
    pos_radius_m: float = 25.0,
) -> SvmBank:
    """The bank by source: ``collection`` (the references, plus ``train``) or ``train`` (those photos only)."""
    if source == "collection":
        return fit_bank_from_collection(pipeline, index, refs, params, train, pos_radius_m=pos_radius_m)
    if source == "train":
        return fit_bank(pipeline, index, refs, train, params, pos_radius_m=pos_radius_m)
    raise ValueError(f"an SVM bank learns from collection or train, not {source!r}")
