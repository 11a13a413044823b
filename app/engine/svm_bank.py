"""The SVM bank: predict which local features of a query are worth aggregating (thesis ch. 5 and 6,
after Kim et al., ICCV 2015).

Why: a tree, a parked car or a generic window appears all over a city; its features match far-away
references as well as the right one and pull the query's descriptor towards the wrong places. Training
photos with GPS tell us, without any manual labels, which of their features matched the right place and
which matched confusers far away. Local features are clustered (appearance varies too much for one linear
model) and one linear SVM per cluster learns "good" against "confusing". At query time each feature goes
to its cluster's SVM; the decision value is its confidence, and only confident features are aggregated,
never fewer than a floor.

Two kinds of labels, selectable by name:
- ``contrastive`` (chapter 5): positive when a feature matches the positives clearly better than the
  confusers, negative when it matches the confusers clearly better; ambiguous features are left out.
- ``confusers`` (chapter 6): learn the confusing features from far-away matches only: a feature that
  matches a confuser strongly is negative, every other feature positive.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from app.engine.artifacts import data_hash, load_artifact, save_artifact
from app.engine.pca import l2_normalize

BANK_KIND, BANK_VERSION = "svm-bank", 1
KINDS = ("contrastive", "confusers")


@dataclass(frozen=True)
class BankParams:
    kind: str = "contrastive"
    n_clusters: int = 16
    margin: float = 0.05  # contrastive: |s_pos - s_neg| needed for a label
    confuser_quantile: float = 0.7  # confusers: s_neg above this quantile of all s_neg is "confusing"
    hard_rounds: int = 3
    C: float = 0.1
    max_negatives_per_round: int = 4000
    seed: int = 0


def match_scores(query: np.ndarray, others: list[np.ndarray]) -> np.ndarray:
    """For each query feature, its best cosine similarity to any feature of ``others`` (-1 if none)."""
    q = l2_normalize(np.asarray(query, np.float32))
    pool = [o for o in others if len(o)]
    if not pool or not len(q):
        return np.full(len(q), -1.0, np.float32)
    best = np.full(len(q), -1.0, np.float32)
    for o in pool:
        best = np.maximum(best, (q @ l2_normalize(np.asarray(o, np.float32)).T).max(axis=1))
    return best


def label_features(
    query: np.ndarray,
    positives: list[np.ndarray],
    confusers: list[np.ndarray],
    params: BankParams,
    neg_threshold: float | None = None,
) -> np.ndarray:
    """+1 (worth keeping), -1 (confusing) or 0 (no label) for each local feature of one training photo."""
    return labels_from_scores(
        match_scores(query, positives), match_scores(query, confusers), bool(positives), params, neg_threshold
    )


def labels_from_scores(
    s_pos: np.ndarray, s_neg: np.ndarray, has_positives: bool, params: BankParams, neg_threshold: float | None = None
) -> np.ndarray:
    """The thesis's thresholded difference (contrastive) or a threshold on confuser matches alone
    (confusers). ``neg_threshold``: the s_neg above which a feature counts as confusing; by default the
    ``confuser_quantile`` of this photo's own s_neg (training passes one threshold for all photos)."""
    thr = (
        neg_threshold
        if neg_threshold is not None
        else float(np.quantile(s_neg, params.confuser_quantile))
        if len(s_neg)
        else 1.0
    )
    labels = np.zeros(len(s_neg), np.int8)
    if params.kind == "contrastive":
        if has_positives:
            labels[s_pos - s_neg > params.margin] = 1
            labels[s_neg - s_pos > params.margin] = -1
        else:  # nothing to contrast with: only a strong confuser match speaks
            labels[s_neg > thr] = -1
    elif params.kind == "confusers":
        labels[:] = 1
        labels[s_neg > thr] = -1
    else:
        raise ValueError(f"unknown SVM bank kind {params.kind!r}; choose one of {KINDS}")
    return labels


class SvmBank:
    def __init__(
        self,
        centers: np.ndarray,
        coef: np.ndarray,
        intercept: np.ndarray,
        params: BankParams,
        threshold: float = 0.0,
        min_keep: int = 50,
        manifest: dict | None = None,
    ):
        self.centers = np.ascontiguousarray(centers, np.float32)
        self.coef = np.ascontiguousarray(coef, np.float32)
        self.intercept = np.asarray(intercept, np.float32)
        self.params = params
        self.threshold = float(threshold)
        self.min_keep = int(min_keep)
        self.manifest = manifest or {}
        self._sq = (self.centers**2).sum(1)

    def cluster_of(self, x: np.ndarray) -> np.ndarray:
        return np.argmin(self._sq[None, :] - 2 * x @ self.centers.T, axis=1)

    def decision(self, x: np.ndarray) -> np.ndarray:
        """Each feature's decision value from its own cluster's SVM: its confidence of being useful."""
        x = np.asarray(x, np.float32)
        if not len(x):
            return np.zeros(0, np.float32)
        c = self.cluster_of(x)
        return np.einsum("nd,nd->n", x, self.coef[c]) + self.intercept[c]

    def keep(self, x: np.ndarray, select: str = "positive") -> np.ndarray:
        """Boolean mask of the features to aggregate. ``positive``: decision above the threshold;
        ``negative``: the others (the thesis ablation). Never fewer than ``min_keep`` (or all, if fewer
        exist): when too few pass, the best-scored ones (for ``negative``, the worst) make up the floor."""
        d = self.decision(x)
        n = len(d)
        mask = d > self.threshold if select == "positive" else d <= self.threshold
        floor = min(self.min_keep, n)
        if mask.sum() < floor:
            order = np.argsort(-d if select == "positive" else d, kind="stable")
            mask = np.zeros(n, bool)
            mask[order[:floor]] = True
        return mask

    @classmethod
    def train(cls, x: np.ndarray, labels: np.ndarray, params: BankParams) -> SvmBank:
        """Cluster the labelled features, then one balanced linear SVM per cluster with a few rounds of
        hard-negative mining (start from a sample of negatives, add the ones the SVM gets most wrong)."""
        from sklearn.cluster import MiniBatchKMeans  # training only: serving never pays scikit-learn's import
        from sklearn.svm import LinearSVC

        keep = labels != 0
        x = np.asarray(x, np.float32)[keep]
        y = labels[keep]
        rng = np.random.default_rng(params.seed)
        k = max(1, min(params.n_clusters, len(x) // 50))
        km = MiniBatchKMeans(n_clusters=k, n_init=3, random_state=params.seed, batch_size=4096).fit(x)
        assign = km.labels_
        d = x.shape[1]
        coef = np.zeros((k, d), np.float32)
        intercept = np.zeros(k, np.float32)
        stats = []
        for c in range(k):
            xc, yc = x[assign == c], y[assign == c]
            n_pos, n_neg = int((yc > 0).sum()), int((yc < 0).sum())
            if n_pos == 0 or n_neg == 0:
                # A cluster with one label: a constant decision (+2 or -2) says so for every member.
                intercept[c] = 2.0 if n_pos else -2.0
                stats.append({"cluster": c, "positives": n_pos, "negatives": n_neg, "train_accuracy": 1.0})
                continue
            pos_idx = np.flatnonzero(yc > 0)
            neg_idx = np.flatnonzero(yc < 0)
            active = rng.permutation(neg_idx)[: params.max_negatives_per_round]
            svm = None
            for _ in range(max(1, params.hard_rounds)):
                idx = np.concatenate([pos_idx, active])
                svm = LinearSVC(
                    C=params.C, class_weight="balanced", dual="auto", max_iter=5000, random_state=params.seed
                ).fit(xc[idx], yc[idx])
                scores = svm.decision_function(xc[neg_idx])
                hard = neg_idx[np.argsort(-scores)[: params.max_negatives_per_round // 2]]
                new = np.setdiff1d(hard, active)
                if not len(new):
                    break
                active = np.concatenate([active, new])
            coef[c], intercept[c] = svm.coef_[0], svm.intercept_[0]
            acc = float(np.mean(np.sign(xc @ coef[c] + intercept[c]) == yc))
            stats.append({"cluster": c, "positives": n_pos, "negatives": n_neg, "train_accuracy": round(acc, 4)})
        manifest = {"n_features": int(len(x)), "data_hash": data_hash(x, y.astype(np.int8)), "clusters": stats}
        return cls(km.cluster_centers_, coef, intercept, params, manifest=manifest)

    def save(self, directory: Path, name: str = "svm_bank") -> None:
        save_artifact(
            directory,
            name,
            BANK_KIND,
            BANK_VERSION,
            {**asdict(self.params), "threshold": self.threshold, "min_keep": self.min_keep},
            {"centers": self.centers, "coef": self.coef, "intercept": self.intercept},
            {"fit": self.manifest},
        )

    @classmethod
    def load(cls, directory: Path, name: str = "svm_bank") -> SvmBank:
        m, a = load_artifact(directory, name, BANK_KIND, BANK_VERSION)
        p = dict(m["params"])
        threshold, min_keep = p.pop("threshold"), p.pop("min_keep")
        return cls(a["centers"], a["coef"], a["intercept"], BankParams(**p), threshold, min_keep, m.get("fit"))

    @staticmethod
    def exists(directory: Path, name: str = "svm_bank") -> bool:
        return (directory / f"{name}.json").exists()
