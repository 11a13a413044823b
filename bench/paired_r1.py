"""Paired R@1 of two ``geoloc eval --json`` runs on the same queries: how many queries' first candidate
became right (wins) and wrong (losses) from the baseline to the variant, with a two-sided sign test.

Why: on 40 queries a difference of two or three in R@1 is within chance; the paired counts and the sign
test say whether a variant's gain is more than that (results.md reports them beside each variant).

    .venv/bin/python -m bench.paired_r1 out/eval/i33-default-40.json out/eval/i33-ms448-40.json
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from math import comb
from pathlib import Path

from app.engine.geo import haversine_m


def hits_at_1(eval_json: Path) -> dict[tuple[str, int | None, float, float], bool]:
    """Whether each query's first candidate lies within the run's radius, keyed by (image, fold, lat, lon)."""
    run = json.loads(eval_json.read_text())
    out = {}
    for q in run["queries"]:
        c = q["candidates"]
        hit = bool(c) and float(haversine_m(q["lat"], q["lon"], c[0][0], c[0][1])) <= run["radius_m"]
        out[(q["image"], q.get("fold"), round(q["lat"], 7), round(q["lon"], 7))] = hit
    return out


def sign_test(wins: int, losses: int) -> float:
    """Two-sided exact sign test (ties left out): the chance of a split at least this uneven."""
    n = wins + losses
    if n == 0:
        return 1.0
    tail = sum(comb(n, k) for k in range(min(wins, losses) + 1)) / 2**n
    return min(1.0, 2 * tail)


def paired(baseline: Path, variant: Path) -> dict:
    a, b = hits_at_1(baseline), hits_at_1(variant)
    common = a.keys() & b.keys()
    wins = sum(b[k] and not a[k] for k in common)
    losses = sum(a[k] and not b[k] for k in common)
    return {"queries": len(common), "wins": wins, "losses": losses, "p": round(sign_test(wins, losses), 3)}


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("baseline", type=Path)
    ap.add_argument("variants", type=Path, nargs="+")
    a = ap.parse_args(argv)
    for v in a.variants:
        print(json.dumps({"variant": v.name, **paired(a.baseline, v)}))


if __name__ == "__main__":
    main()
