"""Choose the fused estimate's temperature and confidence threshold, cross-validated over evaluation folds.

    .venv/bin/python bench/calibrate_estimate.py --eval out/eval/hybrid.json

Input: the per-query records (candidates with scores, true position, fold) that ``geoloc eval --json``
writes. For every (temperature, min_confidence) on a grid we know, per query, whether the estimate is
confident and whether it lies within the radius. Cross-validation keeps the choice honest: for each fold,
the setting with the best coverage among those reaching the target precision is chosen on the *other*
folds and measured on this one; the pooled held-out figures are what users can expect. The setting to
ship is then chosen the same way on all folds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from app.engine.estimate import fuse_position
from app.engine.geo import haversine_m

REPO = Path(__file__).resolve().parents[1]
TEMPERATURES = (0.005, 0.01, 0.02, 0.04, 0.06, 0.08, 0.16)
THRESHOLDS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def outcomes(queries: list[dict], temperature: float, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(confidence, estimate within radius) per query."""
    conf, ok = [], []
    for q in queries:
        c = np.asarray(q["candidates"], float).reshape(-1, 3)
        e = fuse_position(c[:, 0], c[:, 1], c[:, 2], radius_m, temperature=temperature, min_confidence=0.0)
        conf.append(e.confidence)
        ok.append(e.lat is not None and bool(haversine_m(q["lat"], q["lon"], e.lat, e.lon) <= radius_m))
    return np.array(conf), np.array(ok)


def choose(table: dict, train: np.ndarray, target: float, min_selected: int = 10):
    """Best coverage on ``train`` among settings whose precision there reaches ``target``."""
    best = None
    for (temp, thr), (conf, ok) in table.items():
        sel = train & (conf >= thr)
        if sel.sum() < min_selected:
            continue
        precision, coverage = ok[sel].mean(), sel.sum() / train.sum()
        if precision >= target and (best is None or coverage > best[2]):
            best = (temp, thr, coverage, precision)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--eval", type=Path, default=REPO / "out/eval/hybrid.json", help="geoloc eval --json output")
    ap.add_argument("--target-precision", type=float, default=0.7)
    args = ap.parse_args()
    result = json.loads(args.eval.read_text())
    queries, radius = result["queries"], result["radius_m"]
    folds = np.array([q["fold"] for q in queries])
    table = {}
    print(f"{result['config']}: {len(queries)} queries, {result['folds']} folds, radius {radius} m")
    print("temperature  min_conf  coverage  precision")
    for temp in TEMPERATURES:
        conf, ok = outcomes(queries, temp, radius)
        for thr in THRESHOLDS:
            table[(temp, thr)] = (conf, ok)
            sel = conf >= thr
            prec = f"{ok[sel].mean():9.2f}" if sel.any() else "      n/a"
            print(f"{temp:11.3f}  {thr:8.2f}  {sel.mean():8.2f}  {prec}")
    held_sel = held_ok = 0
    for k in sorted(set(folds)):
        best = choose(table, folds != k, args.target_precision)
        if best is None:
            print(f"fold {k}: no setting reaches the target on the other folds")
            continue
        conf, ok = table[best[:2]]
        sel = (folds == k) & (conf >= best[1])
        held_sel += sel.sum()
        held_ok += ok[sel].sum()
        print(f"fold {k}: chose temperature {best[0]}, min_confidence {best[1]} on the other folds")
    print(
        f"cross-validated: confident on {held_sel / len(queries):.1%} of queries, "
        f"within {radius} m on {held_ok / max(held_sel, 1):.1%} of those"
    )
    final = choose(table, np.ones(len(queries), bool), args.target_precision)
    print("setting to ship (chosen on all folds):", final)


if __name__ == "__main__":
    main()
