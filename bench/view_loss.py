"""Where recall is lost (issue 33, item 3): does any reference within 25 m share a verifiable view with the
query, and what is R@1 among the queries that have one and those that do not?

Why: a miss on a query whose place no reference shows from a similar viewpoint cannot be recovered by any
appearance method; a miss on a query with a verifiable view can. A view is *verifiable* when RootSIFT
matching and the H-or-F RANSAC of app/engine/matchers/geometry.py find more inliers between the query and one of the
references within ``radius`` m (another capture, in the query's database; the ``max_near`` nearest) than
a far-pair baseline: the most inliers (``quantile`` 1.0) among ``far_per_query`` pairs per query with
references farther than ``far_m`` (those cannot show the same scene: their inliers are chance, about 14
with this matcher's permissive ratio test and F's freedom, which is why a single pair's quantile will not do
against the best of several near references).

The database of each query is the one ``geoloc eval`` gives it (the same folds, the same groups kept apart),
and R@1 is read from that evaluation's JSON (``--json``), one or several runs, so the split by verifiability
can be computed for any configuration without re-running it.

    .venv/bin/python -m bench.view_loss --manifest data/manifests/penn-campus-gps.csv --folds 5 \\
        --eval out/eval/fix5-lite2-hybrid-384.json --out out/eval/view-loss-5fold.json
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from app.engine.artifacts import atomic_write_bytes
from app.engine.geo import haversine_m
from app.engine.imageio import load_image
from app.engine.matchers.sift_mnn import PixelFeatures, features_for_verification, verify_features
from app.evaluation.datasets import Row, read_manifest
from app.evaluation.evaluate import assign_folds


def query_databases(rows: list[Row], folds: int, seed: int = 0) -> list[tuple[int, list[int]]]:
    """(query row, its database rows) for every query of ``geoloc eval --folds`` (1: the manifest's split)."""
    sets = [[r.group for r in rows if r.split == "query"]] if folds <= 1 else assign_folds(rows, folds, seed)
    out = []
    for qgroups in sets:
        qset = set(qgroups)
        db = [i for i, r in enumerate(rows) if r.group not in qset and r.split != "train"]
        out += [(i, db) for i, r in enumerate(rows) if r.group in qset and r.split != "train"]
    return out


def _features(rows: list[Row], workers: int, cache: Path | None = None) -> list[PixelFeatures]:
    """RootSIFT for verification of every row, read from and added to ``cache`` (a pickle keyed by image
    path, size and mtime: the 40-photo split's images are all in penn-campus-gps)."""
    stored: dict[str, PixelFeatures] = {}
    if cache is not None and cache.exists():
        stored = pickle.loads(cache.read_bytes())

    def key(r: Row) -> str:
        st = r.image.stat()
        return f"{r.image.resolve()}:{st.st_size}:{st.st_mtime_ns}"

    def one(r: Row) -> PixelFeatures:
        return stored.get(key(r)) or features_for_verification(load_image(r.image.read_bytes()).rgb)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        feats = list(pool.map(one, rows))
    if cache is not None:
        stored.update({key(r): f for r, f in zip(rows, feats, strict=True)})
        cache.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(cache, pickle.dumps(stored, protocol=pickle.HIGHEST_PROTOCOL))
    return feats


def analyse(
    rows: list[Row],
    pairs: Sequence[tuple[int, list[int]]],
    radius_m: float = 25.0,
    far_m: float = 100.0,
    far_per_query: int = 10,
    quantile: float = 1.0,
    workers: int = 2,
    seed: int = 0,
    max_near: int | None = None,
    cache: Path | None = None,
) -> dict:
    """Per query: the most inliers with a reference within ``radius_m`` and whether that beats the far-pair
    threshold. Near references are tried nearest first (at most ``max_near``) and the search stops at the
    first that beats it."""
    t0 = time.perf_counter()
    feats = _features(rows, workers, cache)
    lat = np.array([r.lat for r in rows])
    lon = np.array([r.lon for r in rows])
    rng = np.random.default_rng(seed)
    far_inliers = []
    for q, db in pairs:
        d = haversine_m(lat[q], lon[q], lat[db], lon[db])
        far = [db[k] for k in np.flatnonzero(d > far_m)]
        for j in rng.choice(far, min(far_per_query, len(far)), replace=False) if far else []:
            far_inliers.append(verify_features(feats[q], feats[int(j)]).inliers)
    threshold = float(np.quantile(far_inliers, quantile)) if far_inliers else 0.0
    per_query = {}
    for q, db in pairs:
        d = haversine_m(lat[q], lon[q], lat[db], lon[db])
        near = [db[k] for k in np.argsort(d) if d[k] <= radius_m]
        best, tried = 0, 0
        for j in near[:max_near]:
            tried += 1
            best = max(best, verify_features(feats[q], feats[j]).inliers)
            if best > threshold:
                break
        per_query[q] = {"near": len(near), "tried": tried, "best_inliers": best, "verifiable": best > threshold}
    return {
        "threshold_inliers": threshold,
        "far_pairs": len(far_inliers),
        "far_inliers_median": float(np.median(far_inliers)) if far_inliers else None,
        "quantile": quantile,
        "radius_m": radius_m,
        "far_m": far_m,
        "max_near": max_near,
        "seconds": time.perf_counter() - t0,
        "per_query": per_query,
    }


def hits_at_1(rows: list[Row], eval_json: Path, radius_m: float) -> dict[tuple[str, float, float], bool]:
    """Whether each query's first candidate lies within ``radius_m``, keyed by (image name, lat, lon)."""
    out = {}
    for q in json.loads(eval_json.read_text())["queries"]:
        c = q["candidates"]
        hit = bool(c) and float(haversine_m(q["lat"], q["lon"], c[0][0], c[0][1])) <= radius_m
        out[(q["image"], round(q["lat"], 7), round(q["lon"], 7))] = hit
    return out


def summarise(rows: list[Row], result: dict, evals: Sequence[Path], radius_m: float) -> dict:
    """Share of verifiable queries and R@1 among them, for full photos and for crops (224 px) apart."""
    kinds = {"photos": lambda r: "crops" not in r.image.parts, "crops": lambda r: "crops" in r.image.parts}
    summary: dict = {}
    for kind, is_kind in kinds.items():
        qs = [q for q in result["per_query"] if is_kind(rows[q])]
        ver = [q for q in qs if result["per_query"][q]["verifiable"]]
        entry: dict = {"queries": len(qs), "verifiable": len(ver), "share": len(ver) / max(len(qs), 1)}
        entry["no_reference_within_radius"] = sum(result["per_query"][q]["near"] == 0 for q in qs)
        for path in evals:
            hits = hits_at_1(rows, path, radius_m)

            def r1(sel: list[int], hits: dict = hits) -> float | None:
                got = [
                    hits[k]
                    for q in sel
                    if (k := (rows[q].image.name, round(rows[q].lat, 7), round(rows[q].lon, 7))) in hits
                ]
                return float(np.mean(got)) if got else None

            entry[path.name] = {
                "r1_all": r1(qs),
                "r1_verifiable": r1(ver),
                "r1_not_verifiable": r1([q for q in qs if q not in set(ver)]),
            }
        summary[kind] = entry
    return summary


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--manifest", type=Path, required=True)
    ap.add_argument("--folds", type=int, default=1)
    ap.add_argument("--radius-m", type=float, default=25.0)
    ap.add_argument("--far-m", type=float, default=100.0)
    ap.add_argument("--eval", type=Path, nargs="*", default=[], help="geoloc eval --json outputs to split R@1 by")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-near", type=int, default=10, help="try at most this many references within the radius")
    ap.add_argument("--far-per-query", type=int, default=10)
    ap.add_argument("--cache", type=Path, default=Path("out/cache/verify-features.pkl"))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--reuse", action="store_true", help="read the verification outcomes from --out again")
    a = ap.parse_args(argv)
    rows = read_manifest(a.manifest)
    if a.reuse:  # only the R@1 split is recomputed (for other evaluations of the same queries)
        result = json.loads(a.out.read_text())
        result["per_query"] = {int(k.rsplit("@", 1)[1]): v for k, v in result["per_query"].items()}
    else:
        pairs = query_databases(rows, a.folds)
        result = analyse(
            rows, pairs, a.radius_m, a.far_m, a.far_per_query, workers=a.workers, max_near=a.max_near, cache=a.cache
        )
    result["summary"] = summarise(rows, result, a.eval, a.radius_m)
    result["per_query"] = {rows[q].image.name + f"@{q}": v for q, v in result["per_query"].items()}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "per_query"}, indent=1))


if __name__ == "__main__":
    main()
