"""Calibrate what an answer promises: the estimate's radius and each candidate's probability of being right.

    .venv/bin/python bench/calibrate_answers.py --eval out/eval/hybrid.json [--coverage 0.8]

Input: the per-query records of a `geoloc eval --folds 5 --json` run (candidates with scores, the truth,
the fold). Both fits are cross-validated over those folds: chosen on four folds' queries, measured on the
fifth, pooled; the shipped values are then fitted on all folds.

1. Radius. A confident estimate's radius is ``max(farthest fused candidate + margin, floor)``: never
   smaller than the spread of the candidates it was made of. The margin is the smallest on a grid for which
   the truth lies within the radius for ``--coverage`` of the confident answers.
2. Candidate probability, one mapping for a whole evaluation set: a logistic regression of "this candidate
   lies within 25 m of the photo" on the evidence of app/engine/evidence.py (global columns). Reported: the
   held-out Brier score (against a constant's) and a reliability table. Since issue 20 the service fits
   this on each collection itself (app/engine/calibration.py); this pooled fit is kept as a reference.
Prints the radius margin to put in app/engine/estimate.py.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from sklearn.linear_model import LogisticRegression

from app.engine.estimate import fuse_position
from app.engine.evidence import gather
from app.engine.geo import haversine_m

REPO = Path(__file__).resolve().parents[1]
MARGINS = tuple(range(0, 205, 5))


def per_query(queries: list[dict], radius_m: float):
    """For each query: the estimate (margin 0), its farthest member, the truth's distance, candidate rows."""
    out = []
    for q in queries:
        c = np.asarray(q["candidates"], float).reshape(-1, 3)[:10]
        if not len(c):
            continue
        e = fuse_position(c[:, 0], c[:, 1], c[:, 2], radius_m, margin_m=0.0, min_radius_m=0.0)
        truth = float(haversine_m(q["lat"], q["lon"], e.lat, e.lon))
        d_true = haversine_m(q["lat"], q["lon"], c[:, 0], c[:, 1])
        feats = gather(c[:, 0], c[:, 1], c[:, 2]).values
        out.append({"fold": q["fold"], "e": e, "truth_m": truth, "X": feats, "y": (d_true <= radius_m).astype(int)})
    return out


def choose_margin(rows: list[dict], coverage: float, floor: float) -> float:
    conf = [r for r in rows if r["e"].confident]
    for m in MARGINS:
        radius = np.array([max(r["e"].radius_m + m, floor) for r in conf])
        inside = np.array([r["truth_m"] for r in conf]) <= radius
        if inside.mean() >= coverage:
            return float(m)
    return float(MARGINS[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--eval", type=Path, default=REPO / "out/eval/hybrid.json")
    ap.add_argument("--coverage", type=float, default=0.8, help="share of confident answers within the radius")
    ap.add_argument("--floor", type=float, default=10.0, help="smallest radius stated, metres")
    args = ap.parse_args()
    result = json.loads(args.eval.read_text())
    rows = per_query(result["queries"], result["radius_m"])
    folds = sorted({r["fold"] for r in rows})
    print(f"{result['config']}: {len(rows)} queries, {len(folds)} folds")

    held_in = held_n = 0
    for k in folds:
        m = choose_margin([r for r in rows if r["fold"] != k], args.coverage, args.floor)
        test = [r for r in rows if r["fold"] == k and r["e"].confident]
        inside = [r["truth_m"] <= max(r["e"].radius_m + m, args.floor) for r in test]
        held_in += sum(inside)
        held_n += len(inside)
        print(f"fold {k}: margin {m:.0f} m chosen on the other folds; {sum(inside)}/{len(inside)} within radius")
    print(f"radius, cross-validated: truth within the stated radius for {held_in / max(held_n, 1):.1%} of confident")
    margin = choose_margin(rows, args.coverage, args.floor)
    conf = [r for r in rows if r["e"].confident]
    radii = [max(r["e"].radius_m + margin, args.floor) for r in conf]
    print(f"MARGIN_M = {margin:.0f}, RADIUS_FLOOR_M = {args.floor:.0f} (median stated radius {np.median(radii):.0f} m)")

    X = np.vstack([r["X"] for r in rows])
    y = np.concatenate([r["y"] for r in rows])
    fold_of = np.concatenate([[r["fold"]] * len(r["y"]) for r in rows])
    p_held = np.zeros(len(y))
    for k in folds:
        model = LogisticRegression(C=1.0, max_iter=1000).fit(X[fold_of != k], y[fold_of != k])
        p_held[fold_of == k] = model.predict_proba(X[fold_of == k])[:, 1]
    base = np.array([y[fold_of != k].mean() for k in fold_of])
    brier, brier0 = np.mean((p_held - y) ** 2), np.mean((base - y) ** 2)
    print(f"candidate probability, cross-validated: Brier {brier:.4f} (constant rate {brier0:.4f})")
    print("reliability (held out): predicted -> observed (n)")
    bins = np.array([0, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0001])
    for lo, hi in zip(bins[:-1], bins[1:], strict=True):
        sel = (p_held >= lo) & (p_held < hi)
        if sel.any():
            print(f"  {lo:.1f}-{min(hi, 1):.1f}: {p_held[sel].mean():.2f} -> {y[sel].mean():.2f} ({sel.sum()})")
    final = LogisticRegression(C=1.0, max_iter=1000).fit(X, y)
    print("COEF =", [round(float(c), 4) for c in final.coef_[0]], " INTERCEPT =", round(float(final.intercept_[0]), 4))


if __name__ == "__main__":
    main()
