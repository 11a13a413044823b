"""The SVM bank that `geoloc refit` trains, as served: recall of a manifest's query rows on data dirs.

Each data dir is a collection after `geoloc refit` (one with ``--svm-bank collection``, one with
``--svm-bank none``...); every query row is located through the application core exactly as /locate does
(the served generation's pipeline, its bank applied to the query), and a query counts as found at N when one
of its first N candidates lies within ``--radius-m`` of its true position. The first dir is the baseline of
the printed differences.

    python bench/refit_ablation.py --manifest data/manifests/penn-campus-gps.csv \\
        --data-dir /tmp/refit-demo/data-none --data-dir /tmp/refit-demo/data --models-dir models
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from app.domain import LocateOptions
from app.engine.geo import haversine_m
from app.evaluation.datasets import read_manifest
from app.service import GeolocService


def recall(service: GeolocService, rows, radius_m: float) -> dict:
    hits = {1: 0, 5: 0, 10: 0}
    ms = []
    for r in rows:
        t0 = time.perf_counter()
        answer = service.locate(r.image.read_bytes(), LocateOptions(top_k=10))
        ms.append((time.perf_counter() - t0) * 1000)
        d = np.array([haversine_m(r.lat, r.lon, c.lat, c.lon) for c in answer.candidates])
        for n in hits:
            hits[n] += bool(len(d) and (d[:n] <= radius_m).any())
    return {
        "generation": service.collection.generation,
        "bank": service.pipeline.bank is not None,
        **{f"r@{n}": h / max(len(rows), 1) for n, h in hits.items()},
        "median_ms": statistics.median(ms) if ms else 0.0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--manifest", type=Path, required=True)
    ap.add_argument("--data-dir", type=Path, action="append", required=True)
    ap.add_argument("--models-dir", type=Path, default=Path("models"))
    ap.add_argument("--split", default="query")
    ap.add_argument("--radius-m", type=float, default=25.0)
    args = ap.parse_args()
    rows = [r for r in read_manifest(args.manifest) if r.split == args.split]
    print(f"{len(rows)} {args.split} rows, found = a candidate within {args.radius_m:.0f} m")
    print("| data dir | generation | bank | R@1 (vs first) | R@5 | R@10 | median locate ms |")
    print("|---|---|---|---|---|---|---|")
    base = None
    for d in args.data_dir:
        res = recall(GeolocService.open(d, args.models_dir, None), rows, args.radius_m)
        base = base if base is not None else res
        print(
            f"| {d} | {res['generation']} | {'yes' if res['bank'] else 'no'} | {res['r@1']:.3f} "
            f"({res['r@1'] - base['r@1']:+.3f}) | {res['r@5']:.3f} | {res['r@10']:.3f} | {res['median_ms']:.1f} |"
        )


if __name__ == "__main__":
    main()
