"""Measure geometric verification on penn-campus-gps: what separates right from wrong candidates, the
H-or-F rule, how many candidates to verify, the fusion weight, scale and floor chosen leave-one-fold-out,
and stored against recomputed reference features.

    geoloc eval --manifest data/manifests/penn-campus-gps.csv --config hybrid --folds 5 --rerank \
        --models-dir models --cache out/cache --json out/eval-rerank.json
    python -m bench.verification out/eval-rerank.json [--stored-sample 40]

The evaluation runs every query through ``app.usecases.locate.locate_features`` with and without verification and
records, per query, the retrieval order (reference, global score, right or wrong) and each verified
pair's outcome (tentative matches, homography and fundamental-matrix inliers): this script analyses those
records, so what it measures is what /locate does. ``--stored-sample`` re-verifies the first 10 candidates
of that many queries with what ingest could store instead (the strongest ``--stored-keypoints``,
positions and descriptors quantised) and with what the core recomputes, and times the recomputation.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from itertools import product
from pathlib import Path

import numpy as np

from app.engine.imageio import load_image
from app.engine.matchers import fusion, geometry, sift_mnn
from app.manifests import read_manifest

WEIGHTS = (0.05, 0.1, 0.2, 0.3, 0.5, 1.0)
SCALES = (10.0, 20.0, 30.0, 50.0, 100.0)
FLOORS = (0, 10, 15, 20, 30)
H_SHARES = (0.5, 0.7, 0.8, 0.9, 1.0)
BYTES_PER_STORED_KEYPOINT = 2 * 2 + 128  # x, y as uint16 pixels; RootSIFT quantised to uint8


def pairs_from_eval(result: dict) -> dict[str, np.ndarray]:
    """One row per (query, retrieved candidate): fold, query, rank, ref, global score, right, and for the
    verified head (tentative matches, H inliers, F inliers; zeros when not verified) and whether it was."""
    rows = []
    for qn, q in enumerate(result["queries"]):
        v = q.get("verification")
        if v is None:
            raise SystemExit("this evaluation ran without --rerank: nothing to analyse")
        for rank, (ref, score, right) in enumerate(v["retrieval"]):
            out = v["pairs"].get(str(ref))
            n, h, f = out[:3] if out is not None else (0, 0, 0)
            # A learned matcher records its matches' mean confidence too (NaN: not recorded).
            conf = out[3] if out is not None and len(out) > 3 and out[3] is not None else np.nan
            crop = "_" in Path(q["image"]).stem.removeprefix("img_")  # penn crops are img_NNNNN_K.jpg
            rows.append([q["fold"], qn, rank, ref, score, right, n, h, f, str(ref) in v["pairs"], crop, conf])
    arr = np.array(rows, float)
    cols = ["fold", "query", "rank", "ref", "score", "correct", "n", "h", "f", "verified", "crop", "conf"]
    P = {c: arr[:, i] for i, c in enumerate(cols)}
    P["qid"] = P["query"].astype(int)
    P["rank"] = P["rank"].astype(int)
    P["correct"] = P["correct"].astype(bool)
    P["verified"] = P["verified"].astype(bool)
    P["crop"] = P["crop"].astype(bool)
    return P


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if len(a) else float("nan")


def _mean(a: np.ndarray) -> float:
    return float(np.mean(a)) if len(a) else float("nan")


def stored_form(f: sift_mnn.PixelFeatures, keypoints: int) -> sift_mnn.PixelFeatures:
    """What ingest could keep: the strongest ``keypoints`` (the extractor sorts by response), pixel
    positions rounded, RootSIFT components (in [0, 1]) quantised to uint8 and back."""
    xy = np.round(f.xy[:keypoints])
    d = np.round(f.descriptors[:keypoints] * 255).astype(np.uint8).astype(np.float32) / 255
    return sift_mnn.PixelFeatures(xy.astype(np.float32), d)


def stored_check(result: dict, manifest: Path, n_queries: int, keypoints: int, seed: int = 0) -> None:
    """Recomputed against stored reference features on the first 10 candidates of a sample of queries."""
    rows = read_manifest(manifest)
    by_name = {r.image.name: i for i, r in enumerate(rows)}
    rng = np.random.default_rng(seed)
    sample = rng.choice(len(result["queries"]), size=min(n_queries, len(result["queries"])), replace=False)
    feats: dict[int, sift_mnn.PixelFeatures] = {}
    ms, kp, rec, sto, lab = [], [], [], [], []

    def vf(i: int) -> sift_mnn.PixelFeatures:
        if i not in feats:
            t0 = time.perf_counter()
            feats[i] = sift_mnn.features_for_verification(load_image(rows[i].image.read_bytes()).rgb)
            ms.append((time.perf_counter() - t0) * 1000)
            kp.append(len(feats[i]))
        return feats[i]

    for qn in sample:
        q = result["queries"][qn]
        qf = vf(by_name[q["image"]])
        for ref, _score, right in q["verification"]["retrieval"][:10]:
            r = vf(ref)
            a, b = sift_mnn.verify_features(qf, r), sift_mnn.verify_features(qf, stored_form(r, keypoints))
            rec.append(a.inliers)
            sto.append(b.inliers)
            lab.append(right)
    rec_a, sto_a, lab_a = np.array(rec), np.array(sto), np.array(lab)
    kb = statistics.median(kp) * BYTES_PER_STORED_KEYPOINT / 1024
    print(f"\nstored against recomputed reference features ({len(sample)} queries, {len(rec)} pairs):")
    print(
        f"  recomputed: median {statistics.median(kp):.0f} keypoints per image (max {max(kp)}), {kb:.0f} KB if "
        f"stored; decode + RootSIFT {statistics.median(ms):.1f} ms per image (median, p90 "
        f"{np.percentile(ms, 90):.1f}); inlier AUC {auc(rec_a, lab_a):.3f}"
    )
    print(
        f"  stored ({keypoints} keypoints, uint8): {keypoints * BYTES_PER_STORED_KEYPOINT / 1024:.0f} KB per "
        f"reference at most; inlier AUC {auc(sto_a, lab_a):.3f}; inliers of right pairs median "
        f"{_pct(sto_a[lab_a == 1], 50):.0f} against {_pct(rec_a[lab_a == 1], 50):.0f} recomputed"
    )


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
    fitted = (n >= geometry.MIN_MATCHES_TO_FIT) & (f > 0)
    use_h = fitted & (h >= h_share * f)
    return np.where(fitted, np.where(use_h, h, f), 0), use_h


def fused(score: np.ndarray, inl: np.ndarray, weight: float, scale: float, floor: float) -> np.ndarray:
    """``fusion.fused_score`` on arrays."""
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


def lofo(P: dict, inl: np.ndarray, k: int, floors: tuple, what: str) -> None:
    """Weight, scale and floor chosen leave-one-fold-out: each fold's figures use the triple chosen on the
    other folds (by R@1, then R@5, then the smaller weight and the larger floor)."""
    nq = len(np.unique(P["qid"]))
    print(f"\nleave-one-fold-out (weight, scale, floor), {what}, K = {k}:")
    held = [0.0, 0.0]
    for f in np.unique(P["fold"]):
        train_q = np.unique(P["qid"][P["fold"] != f])
        test_q = np.unique(P["qid"][P["fold"] == f])
        best = max(
            product(WEIGHTS, SCALES, floors),
            key=lambda ws: (*recall(P, fused(P["score"], inl, *ws), k, train_q), -ws[0], ws[2]),
        )
        r = recall(P, fused(P["score"], inl, *best), k, test_q)
        r0 = recall(P, -P["rank"].astype(float), k, test_q)
        held[0] += r[0] * len(test_q)
        held[1] += r[1] * len(test_q)
        print(
            f"  fold {int(f) + 1}: {best}: held-out R@1 {r[0]:.3f} R@5 {r[1]:.3f} (no rerank {r0[0]:.3f} {r0[1]:.3f})"
        )
    print(f"  pooled held-out: R@1 {held[0] / nq:.3f}  R@5 {held[1] / nq:.3f}")


def analyse(result: dict) -> None:
    P = pairs_from_eval(result)
    lab = P["correct"].astype(int)
    nq = len(np.unique(P["qid"]))
    head = P["verified"]
    k_max = int(P["rank"][head].max()) + 1
    print(
        f"{nq} queries, {len(lab)} retrieved pairs, first {k_max} verified per query ({head.sum()} pairs, "
        f"{lab[head].mean():.1%} of them right)"
    )
    inl, use_h = chosen_inliers(P["h"], P["f"], P["n"], 0.8)
    raw_f = np.where(P["n"] >= geometry.MIN_MATCHES_TO_FIT, P["f"], 0)
    base = recall(P, -P["rank"].astype(float), k_max)
    print(f"no rerank: R@1 {base[0]:.3f}  R@5 {base[1]:.3f}")
    fitted = head & (inl > 0)
    right, wrong = fitted & P["correct"], fitted & ~P["correct"]
    print(
        f"fitted pairs (>= {geometry.MIN_MATCHES_TO_FIT} tentative matches): {fitted.sum() / head.sum():.0%} of "
        f"verified pairs; chosen-model inliers right median {_pct(inl[right], 50):.0f} (p90 "
        f"{_pct(inl[right], 90):.0f}), wrong median {_pct(inl[wrong], 50):.0f} (p90 "
        f"{_pct(inl[wrong], 90):.0f}, p99 {_pct(inl[wrong], 99):.0f})"
    )

    wrong_p99 = _pct(inl[wrong], 99)
    lofo(P, inl, k_max, FLOORS, "any floor")
    high = tuple(f for f in FLOORS if f >= wrong_p99)
    if high:
        lofo(P, inl, k_max, high, f"floor >= wrong pairs' p99 ({wrong_p99:.0f})")
    else:  # a matcher that gives wrong pairs many inliers (a learned one on lookalike facades)
        print(f"\nno floor of {FLOORS} reaches the wrong pairs' p99 ({wrong_p99:.0f} inliers)")

    w, s, fl = fusion.FUSION_WEIGHT, fusion.FUSION_SCALE, fusion.FUSION_FLOOR
    fz = fused(P["score"], inl, w, s, fl)
    print(f"\nthe defaults (weight {w}, scale {s:.0f}, floor {fl}) on all queries:")
    for k in sorted({5, k_max}):
        r = recall(P, fz, k)
        raw = recall(P, inl + 1e-6 * P["score"], k)
        print(f"  K {k:<3} fused R@1 {r[0]:.3f} R@5 {r[1]:.3f}   raw chosen inliers R@1 {raw[0]:.3f} R@5 {raw[1]:.3f}")
    print("  separation of right from wrong among verified pairs (AUC):")
    print(
        f"    global {auc(P['score'][head], lab[head]):.3f}  raw F inliers {auc(raw_f[head], lab[head]):.3f}  "
        f"chosen inliers {auc(inl[head], lab[head]):.3f}  fused {auc(fz[head], lab[head]):.3f}"
    )
    has_conf = head & np.isfinite(P["conf"])
    print(
        f"    tentative matches {auc(P['n'][head], lab[head]):.3f}"
        + (f"  mean match confidence {auc(P['conf'][has_conf], lab[has_conf]):.3f}" if has_conf.any() else "")
    )
    per_q = []
    for qid in np.unique(P["qid"][head]):  # within a query: does the fused score rank right above wrong?
        m = head & (P["qid"] == qid)
        if 0 < P["correct"][m].sum() < m.sum():
            per_q.append((auc(P["score"][m], lab[m]), auc(fz[m], lab[m]), auc(raw_f[m], lab[m])))
    g, fu, rf = np.mean(per_q, axis=0) if per_q else (float("nan"),) * 3
    print(
        f"    per query (mean over {len(per_q)} queries with right and wrong candidates): global {g:.3f}  "
        f"raw F inliers {rf:.3f}  fused {fu:.3f}"
    )

    print(f"  by query kind (defaults, K = {k_max}):")
    for name, kind in (("photos", ~P["crop"]), ("224 px crops", P["crop"])):
        qs = np.unique(P["qid"][kind])
        r0, r1 = recall(P, -P["rank"].astype(float), k_max, qs), recall(P, fz, k_max, qs)
        rk, wk = right & kind, wrong & kind
        print(
            f"    {name}: {len(qs)} queries, R@1 {r0[0]:.3f} -> {r1[0]:.3f}, R@5 {r0[1]:.3f} -> {r1[1]:.3f}; "
            f"median tentative matches {_pct(P['n'][head & kind], 50):.0f}; inliers right median "
            f"{_pct(inl[rk], 50):.0f} (p90 {_pct(inl[rk], 90):.0f}), wrong {_pct(inl[wk], 50):.0f} "
            f"(p99 {_pct(inl[wk], 99):.0f}); AUC fused {auc(fz[head & kind], lab[head & kind]):.3f} "
            f"global {auc(P['score'][head & kind], lab[head & kind]):.3f}"
        )

    print("\nthe H-or-F rule (H kept when its inliers >= h_share x F's), fitted pairs:")
    for hs in H_SHARES:
        i2, h2 = chosen_inliers(P["h"], P["f"], P["n"], hs)
        fit = head & (i2 > 0)
        r = recall(P, fused(P["score"], i2, w, s, fl), k_max)
        print(
            f"  h_share {hs:.1f}: H for {_mean(h2[fit]):.0%} (right pairs {_mean(h2[fit & P['correct']]):.0%}, "
            f"wrong {_mean(h2[fit & ~P['correct']]):.0%}); AUC chosen inliers {auc(i2[head], lab[head]):.3f}; "
            f"R@1 {r[0]:.3f} R@5 {r[1]:.3f}"
        )


def by_distance(result: dict, bins=(0, 25, 50, 100, 200)) -> None:
    """Chosen-model inliers of the verified pairs by the distance between query and candidate: evidence of
    scene overlap only counts for "within 25 m" if it falls with the distance."""
    from app.engine.geo import haversine_m

    rows = read_manifest(Path(result["manifest"]))
    by_name = {r.image.name: i for i, r in enumerate(rows)}
    dist, inl = [], []
    for q in result["queries"]:
        qi = by_name[q["image"]]
        for ref, out in q["verification"]["pairs"].items():
            if out is None:
                continue
            i, _ = chosen_inliers(np.array([out[1]]), np.array([out[2]]), np.array([out[0]]), 0.8)
            dist.append(haversine_m(rows[qi].lat, rows[qi].lon, rows[int(ref)].lat, rows[int(ref)].lon))
            inl.append(float(i[0]))
    d, n = np.array(dist), np.array(inl)
    print("\nchosen-model inliers by query-candidate distance (verified pairs):")
    for lo, hi in zip(bins, [*bins[1:], np.inf], strict=True):
        m = (d >= lo) & (d < hi)
        if m.any():
            print(
                f"  {lo:>4}-{hi:<5} m: {m.sum():4d} pairs, inliers median {_pct(n[m], 50):.0f} p90 "
                f"{_pct(n[m], 90):.0f}, {np.mean(n[m] >= 40):.0%} with >= 40"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("eval_json", type=Path, help="the JSON of `geoloc eval --rerank --json`")
    ap.add_argument("--stored-sample", type=int, default=0, help="queries for the stored-features check")
    ap.add_argument("--stored-keypoints", type=int, default=480, help="64 KB / 132 B per keypoint = 496")
    args = ap.parse_args()
    result = json.loads(args.eval_json.read_text())
    analyse(result)
    by_distance(result)
    if args.stored_sample:
        stored_check(result, Path(result["manifest"]), args.stored_sample, args.stored_keypoints)


if __name__ == "__main__":
    main()
