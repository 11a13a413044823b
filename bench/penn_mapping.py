"""The penn-fitted mapping the service had before issue 20 (main's app/engine/calibration.py COEF, fitted on
the 5-fold penn-campus-gps evaluation's own queries) and the old confidence rule (the estimate's weight share
>= 0.5), recomputed on a `geoloc eval --json` report's queries, for comparison with the collection's rule:

    .venv/bin/python -m bench.penn_mapping out/eval/hybrid-absent.json

Each query's first 10 candidates (as the report rounds them) are fused again (``fuse_position``); prints per
fold and pooled the Brier score of the mapping's ``p_within_25m`` and the old rule's coverage and precision.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from app.engine.estimate import fuse_position
from app.engine.geo import haversine_m

#: main before issue 20: score, score - best, log(1 + rank), in the estimate's group, estimate confidence.
COEF = (1.9396, 0.7653, -0.1715, 1.6356, 4.1667)
INTERCEPT = -5.0784


def main(path: str) -> None:
    report = json.loads(Path(path).read_text())
    by_fold: dict[int, list] = {}
    for q in report["queries"]:
        c = np.array(q["candidates"][:10], float)
        e = fuse_position(c[:, 0], c[:, 1], c[:, 2])
        n = len(c)
        members = np.zeros(n)
        m = np.asarray(e.members, bool)
        members[: len(m)] = m
        x = np.column_stack(
            [c[:, 2], c[:, 2] - c[:, 2].max(), np.log1p(np.arange(n)), members, np.full(n, e.confidence)]
        )
        p = 1 / (1 + np.exp(-(x @ np.array(COEF) + INTERCEPT)))
        y = haversine_m(q["lat"], q["lon"], c[:, 0], c[:, 1]) <= report["radius_m"]
        right = bool(haversine_m(q["lat"], q["lon"], e.lat, e.lon) <= report["radius_m"])
        by_fold.setdefault(q["fold"], []).append(((p - y) ** 2, e.confidence >= 0.5, right))
    for name, rows in [*((f"fold {f + 1}", v) for f, v in sorted(by_fold.items())), ("all", sum(by_fold.values(), []))]:
        brier = float(np.concatenate([r[0] for r in rows]).mean())
        conf = [r[2] for r in rows if r[1]]
        print(
            f"{name}: penn mapping Brier {brier:.3f}; old rule confident {len(conf) / len(rows):.1%}, "
            f"within {report['radius_m']:.0f} m {np.mean(conf) if conf else float('nan'):.1%}"
        )


if __name__ == "__main__":
    main(sys.argv[1])
