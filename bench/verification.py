"""Measure geometric verification on penn-campus-gps: what separates right from wrong candidates, the
H-or-F rule, how many candidates to verify, stored against recomputed reference features, and the fusion
weight and scale chosen leave-one-fold-out.

    python -m bench.verification --cache out/cache --pairs out/verification-pairs.json

Step 1 (collect, skipped when ``--pairs`` exists): the same 5 group folds as ``geoloc eval --folds 5``;
each fold fits the pipeline, indexes its db rows, and every query goes through ``core.locate_features``
(no rerank) for its top ``--candidates``; each (query, candidate) pair is then verified with the core's
functions (``rerank.features_for_verification``, ``rerank.verify_features``), once with the features the
core recomputes and once with what could be stored at ingest (the strongest ``--stored-keypoints``,
descriptors quantised to uint8). Step 2 (analyse) prints the figures of docs/RESULTS.md from the pairs.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from itertools import product
from pathlib import Path

import numpy as np

from app.core import LocateOptions, locate_features
from app.datasets import read_manifest
from app.engine import rerank
from app.engine.configs import get_config
from app.engine.geo import haversine_m
from app.engine.imageio import load_image
from app.engine.pipeline import Pipeline
from app.engine.search import ReferenceIndex
from app.evaluate import RowReferences, assign_folds, extract_cached

WEIGHTS = (0.05, 0.1, 0.2, 0.3, 0.5, 1.0)
SCALES = (10.0, 20.0, 30.0, 50.0, 100.0)
FLOORS = (0, 10, 15, 20, 30)
H_SHARES = (0.5, 0.7, 0.8, 0.9, 1.0)
KS = (5, 10, 20)
BYTES_PER_STORED_KEYPOINT = 2 * 2 + 128  # x, y as uint16 pixels; RootSIFT quantised to uint8
COLUMNS = ["fold", "query", "rank", "ref", "score", "correct", "n", "h", "f", "stored_n", "stored_h", "stored_f"]


def stored_form(f: rerank.PixelFeatures, keypoints: int) -> rerank.PixelFeatures:
    """What ingest could keep: the strongest ``keypoints`` (the extractor sorts by response), pixel
    positions rounded, RootSIFT components (in [0, 1]) quantised to uint8 and back."""
    xy = np.round(f.xy[:keypoints])
    d = np.round(f.descriptors[:keypoints] * 255).astype(np.uint8).astype(np.float32) / 255
    return rerank.PixelFeatures(xy.astype(np.float32), d)


def collect(args) -> dict:
    from app.cli import _load_cnn

    rows = read_manifest(args.manifest)
    cfg = get_config(args.config)
    cnn = _load_cnn(args.models_dir, cfg)
    extracted = extract_cached(Pipeline(cfg, cnn=cnn, models_dir=args.models_dir), rows, args.cache)
    feats: dict[int, rerank.PixelFeatures] = {}
    recompute_ms: dict[int, float] = {}

    def vf(i: int) -> rerank.PixelFeatures:
        if i not in feats:
            t0 = time.perf_counter()
            feats[i] = rerank.features_for_verification(load_image(rows[i].image.read_bytes()).rgb)
            recompute_ms[i] = (time.perf_counter() - t0) * 1000
        return feats[i]

    pairs, verify_ms = [], []
    for f, qgroups in enumerate(assign_folds(rows, args.folds, args.seed)):
        qset = set(qgroups)
        q_idx = [i for i, r in enumerate(rows) if r.group in qset and r.split != "train"]
        db_idx = [i for i, r in enumerate(rows) if r.group not in qset and r.split != "train"]
        fit_idx = db_idx + [i for i, r in enumerate(rows) if r.split == "train"]
        pipe = Pipeline(cfg, cnn=cnn, models_dir=args.models_dir)
        pipe.fit([extracted[i].features for i in fit_idx], seed=args.seed + f)
        index = ReferenceIndex(cfg, pipe.float_dim, pipe.bits)
        codes = [pipe.encode_features(extracted[i].features) for i in db_idx]
        index.add(
            np.array(db_idx, np.int64),
            np.stack([c.float_ for c in codes]) if pipe.float_dim else None,
            np.stack([c.binary for c in codes]) if pipe.bits else None,
        )
        refs = RowReferences(rows, db_idx)
        for qi in q_idx:
            res = locate_features(pipe, index, refs, extracted[qi].features, LocateOptions(top_k=args.candidates))
            q = vf(qi)
            for rank, c in enumerate(res.candidates):
                r = vf(c.reference_id)
                t0 = time.perf_counter()
                v = rerank.verify_features(q, r)
                verify_ms.append((time.perf_counter() - t0) * 1000)
                s = rerank.verify_features(q, stored_form(r, args.stored_keypoints))
                d = float(haversine_m(rows[qi].lat, rows[qi].lon, c.lat, c.lon))
                pairs.append(
                    [f, qi, rank, c.reference_id, c.score, int(d <= args.radius_m)]
                    + [v.n_matches, v.h_inliers, v.f_inliers, s.n_matches, s.h_inliers, s.f_inliers]
                )
        print(f"fold {f + 1}: {len(q_idx)} queries, {len(pairs)} pairs so far", flush=True)
    n_kp = [len(x) for x in feats.values()]
    return {
        "columns": COLUMNS,
        "pairs": pairs,
        "keypoints_median": float(statistics.median(n_kp)),
        "recompute_ms_median": float(statistics.median(recompute_ms.values())),
        "verify_ms_median": float(statistics.median(verify_ms)),
        "stored_keypoints": args.stored_keypoints,
    }


# -- analysis ---------------------------------------------------------------------------------------------
def auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Probability that a right candidate scores above a wrong one (ties count half): Mann-Whitney."""
    pos, neg = scores[labels == 1], scores[labels == 0]
    if not len(pos) or not len(neg):
        return float("nan")
    order = np.argsort(np.concatenate([pos, neg]), kind="stable")
    allv = np.concatenate([pos, neg])[order]
    ranks = np.empty(len(allv))
    i = 0
    while i < len(allv):  # average ranks over ties
        j = i
        while j + 1 < len(allv) and allv[j + 1] == allv[i]:
            j += 1
        ranks[i : j + 1] = (i + j) / 2 + 1
        i = j + 1
    r = np.empty(len(allv))
    r[order] = ranks
    return float((r[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def chosen_inliers(h: np.ndarray, f: np.ndarray, n: np.ndarray, h_share: float) -> tuple[np.ndarray, np.ndarray]:
    """The core's rule on recorded counts: (inliers of the chosen model, chose H)."""
    fitted = (n >= rerank.MIN_MATCHES_TO_FIT) & (f > 0)
    use_h = fitted & (h >= h_share * f)
    return np.where(fitted, np.where(use_h, h, f), 0), use_h


def fused(score: np.ndarray, inl: np.ndarray, weight: float, scale: float, floor: float) -> np.ndarray:
    """``rerank.fused_score`` on arrays."""
    return score + weight * (1 - np.exp(-np.maximum(inl - floor, 0) / scale))


def recall(P: dict, key: np.ndarray, k: int, queries: np.ndarray | None = None) -> tuple[float, float]:
    """R@1 and R@5 after re-ordering each query's first ``k`` candidates by ``key`` (the rest keep their
    order, as in the core); ``queries`` restricts to some (query, fold) ids."""
    hits1, hits5 = [], []
    for qid in np.unique(P["qid"]) if queries is None else queries:
        m = np.flatnonzero(P["qid"] == qid)
        m = m[np.argsort(P["rank"][m])]
        head, tail = m[:k], m[k:]
        head = head[np.argsort(-key[head], kind="stable")]
        order = np.concatenate([head, tail])
        hits1.append(P["correct"][order[:1]].any())
        hits5.append(P["correct"][order[:5]].any())
    return float(np.mean(hits1)), float(np.mean(hits5))


def analyse(data: dict) -> None:
    arr = np.array(data["pairs"], float)
    P = {c: arr[:, n] for n, c in enumerate(data["columns"])}
    P["qid"] = P["fold"] * 100000 + P["query"]
    P["rank"] = P["rank"].astype(int)
    P["correct"] = P["correct"].astype(bool)
    lab = P["correct"].astype(int)
    nq = len(np.unique(P["qid"]))
    print(f"{nq} queries, {len(arr)} pairs, right candidates {lab.mean():.1%} of pairs")
    inl, use_h = chosen_inliers(P["h"], P["f"], P["n"], 0.8)
    raw_f = np.where(P["n"] >= rerank.MIN_MATCHES_TO_FIT, P["f"], 0)

    base = recall(P, -P["rank"].astype(float), 1)
    print(f"\nno rerank: R@1 {base[0]:.3f}  R@5 {base[1]:.3f}")

    # The fusion weight and scale, leave-one-fold-out: each fold's figures use the pair chosen on the others.
    folds = np.unique(P["fold"])
    print("\nleave-one-fold-out choice of (weight, scale, floor) by R@1 then R@5 on the other folds, K = 10:")
    lofo_hits = []
    chosen = []
    for f in folds:
        train_q = np.unique(P["qid"][P["fold"] != f])
        test_q = np.unique(P["qid"][P["fold"] == f])
        best = max(
            product(WEIGHTS, SCALES, FLOORS),
            key=lambda ws: (*recall(P, fused(P["score"], inl, *ws), 10, train_q), -ws[0], ws[2]),
        )
        chosen.append(best)
        r = recall(P, fused(P["score"], inl, *best), 10, test_q)
        lofo_hits.append((r[0] * len(test_q), r[1] * len(test_q)))
        print(f"  fold {int(f) + 1}: (weight, scale, floor) {best}: held-out R@1 {r[0]:.3f} R@5 {r[1]:.3f}")
    print(
        f"  pooled held-out: R@1 {sum(h for h, _ in lofo_hits) / nq:.3f}  R@5 {sum(h for _, h in lofo_hits) / nq:.3f}"
    )

    w, s, fl = rerank.FUSION_WEIGHT, rerank.FUSION_SCALE, rerank.FUSION_FLOOR
    print(f"\nseparation of right from wrong candidates (AUC over each query's top K), fused ({w}, {s:.0f}, {fl}):")
    print("  K   global  raw-F-inliers  chosen-inliers  fused")
    for k in KS:
        m = P["rank"] < k
        print(
            f"  {k:<3} {auc(P['score'][m], lab[m]):.3f}   {auc(raw_f[m], lab[m]):.3f}          "
            f"{auc(inl[m], lab[m]):.3f}           {auc(fused(P['score'], inl, w, s, fl)[m], lab[m]):.3f}"
        )

    print(f"\ncandidates verified, K (fused: weight {w}, scale {s:.0f}, floor {fl}; or raw inliers):")
    for k in KS:
        r = recall(P, fused(P["score"], inl, w, s, fl), k)
        raw = recall(P, inl + 1e-6 * P["score"], k)
        print(f"  K {k:<3} fused R@1 {r[0]:.3f} R@5 {r[1]:.3f}   raw chosen inliers R@1 {raw[0]:.3f} R@5 {raw[1]:.3f}")

    print("\nthe H-or-F rule (fitted pairs in the top 10; H kept when H inliers >= h_share x F inliers):")
    m10 = P["rank"] < 10
    for hs in H_SHARES:
        i2, h2 = chosen_inliers(P["h"], P["f"], P["n"], hs)
        fit = m10 & (i2 > 0)
        r = recall(P, fused(P["score"], i2, w, s, fl), 10)
        right, wrong = h2[fit & P["correct"]].mean(), h2[fit & ~P["correct"]].mean()
        print(
            f"  h_share {hs:.1f}: H for {h2[fit].mean():.0%} of fitted pairs (right {right:.0%}, "
            f"wrong {wrong:.0%}); AUC chosen inliers {auc(i2[m10], lab[m10]):.3f}; "
            f"R@1 {r[0]:.3f} R@5 {r[1]:.3f}"
        )
    fitted = m10 & (inl > 0)
    print(
        f"  fitted pairs: {fitted.sum() / m10.sum():.0%} of top-10 pairs; median inliers right "
        f"{np.median(inl[fitted & P['correct']]):.0f}, wrong {np.median(inl[fitted & ~P['correct']]):.0f}"
    )

    st_inl, _ = chosen_inliers(P["stored_h"], P["stored_f"], P["stored_n"], 0.8)
    kp = data["stored_keypoints"]
    r_st = recall(P, fused(P["score"], st_inl, w, s, fl), 10)
    r_re = recall(P, fused(P["score"], inl, w, s, fl), 10)
    print("\nstored against recomputed reference features (K = 10):")
    print(
        f"  recomputed: median {data['keypoints_median']:.0f} keypoints, would take "
        f"{data['keypoints_median'] * BYTES_PER_STORED_KEYPOINT / 1024:.0f} KB stored; decode + RootSIFT "
        f"{data['recompute_ms_median']:.1f} ms per reference (median); AUC {auc(inl[m10], lab[m10]):.3f}; "
        f"R@1 {r_re[0]:.3f} R@5 {r_re[1]:.3f}"
    )
    print(
        f"  stored ({kp} keypoints, uint8): {kp * BYTES_PER_STORED_KEYPOINT / 1024:.0f} KB per reference; "
        f"AUC {auc(st_inl[m10], lab[m10]):.3f}; R@1 {r_st[0]:.3f} R@5 {r_st[1]:.3f}"
    )
    print(f"  matching + H and F fits per pair: {data['verify_ms_median']:.1f} ms (median)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--manifest", type=Path, default=Path("/work/main/data/manifests/penn-campus-gps.csv"))
    ap.add_argument("--models-dir", type=Path, default=Path("/work/main/models"))
    ap.add_argument("--config", default="hybrid")
    ap.add_argument("--cache", type=Path, default=Path("out/cache"))
    ap.add_argument("--pairs", type=Path, default=Path("out/verification-pairs.json"))
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--radius-m", type=float, default=25.0)
    ap.add_argument("--candidates", type=int, default=20)
    ap.add_argument("--stored-keypoints", type=int, default=480, help="64 KB / 132 B per keypoint = 496")
    args = ap.parse_args()
    if args.pairs.exists():
        data = json.loads(args.pairs.read_text())
    else:
        data = collect(args)
        args.pairs.parent.mkdir(parents=True, exist_ok=True)
        args.pairs.write_text(json.dumps(data))
    analyse(data)


if __name__ == "__main__":
    main()
