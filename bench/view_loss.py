"""Where recall is lost (issue 33, item 3): does any reference within 25 m share a verifiable view with the
query, and what is R@1 among the queries that have one and those that do not?

Why: a miss on a query whose place no reference shows from a similar viewpoint cannot be recovered by any
appearance method; a miss on a query with a verifiable view can. A view is *verifiable* when the judge (a
matcher, ``--judge``) finds more inliers between the query and one of the references within ``radius`` m
(another capture, in the query's database; the ``max_near`` nearest) than a far-pair baseline: the most
inliers (``quantile`` 1.0) among ``far_per_query`` pairs per query with references farther than ``far_m``
(those cannot show the same scene: their inliers are chance, about 14 with RootSIFT's permissive ratio test
and F's freedom, which is why a single pair's quantile will not do against the best of several near
references).

Judges (``JUDGES``): ``sift-mnn`` (RootSIFT at 800 px, the core's verification), ``xfeat-lighterglue`` (XFeat
keypoints matched by LighterGlue, the learned matcher: lookalike facades get few, unconfident matches), both
through the matcher registry, and ``stored:xfeat-640-n900`` (the stored-features profile: XFeat, mutual
nearest neighbours, cosine > 0.82, ``app.engine.stored_verification``). Each photo's features are cached on
disk, one file per photo and judge (``--cache-dir``), so a run that stops resumes where it was.

The database of each query is the one ``geoloc eval`` gives it (the same folds, the same groups kept apart),
and R@1 is read from that evaluation's JSON (``--json``), one or several runs, so the split by verifiability
can be computed for any configuration without re-running it.

    .venv/bin/python -m bench.view_loss --manifest data/manifests/penn-campus-gps.csv --folds 5 \\
        --judge xfeat-lighterglue --eval out/eval/fix5-lite2-hybrid-384.json --out out/eval/view-loss-5fold.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.engine.artifacts import atomic_write_bytes
from app.engine.geo import haversine_m
from app.engine.imageio import load_image
from app.engine.registry import Kind, create
from app.engine.stored_profiles import StoredExtractor, get_profile
from app.engine.stored_verification import verify_stored
from app.evaluation.evaluate import assign_folds
from app.manifests import Row, read_manifest

#: The prefix of a judge that is a stored-features profile (``app.engine.stored_profiles``), not a matcher.
STORED = "stored:"
JUDGES = ("sift-mnn", "xfeat-lighterglue", STORED + "xfeat-640-n900")


@dataclass(frozen=True)
class Judge:
    """How a pair is judged: one photo's features (``features``, cached per photo), and the inliers of a
    query against each of some candidates (``inliers``)."""

    name: str
    features: Callable[[np.ndarray], Any]
    inliers: Callable[[Any, Sequence[Any]], list[int]]


def make_judge(name: str, models_dir: Path | None) -> Judge:
    """A matcher of the registry (``sift-mnn``, ``xfeat-lighterglue``), or ``stored:PROFILE``: the stored
    profile's query features against each candidate's stored record, matched as /locate matches them."""
    if name.startswith(STORED):
        profile = get_profile(name[len(STORED) :])
        extractor = StoredExtractor(profile, models_dir)
        extractor.load()

        def stored_inliers(query, candidates):
            out = verify_stored(query[0], [c[1] for c in candidates], settings=profile.settings).verifications
            return [v.inliers if v is not None else 0 for v in out]

        return Judge(name, lambda rgb: (extractor.query(rgb), extractor.record(rgb)), stored_inliers)
    matcher = create(Kind.MATCHER, name, models_dir)
    matcher.load()
    return Judge(name, matcher.features, lambda q, cs: [v.inliers for v in matcher.match_many(q, cs)])


def query_databases(rows: list[Row], folds: int, seed: int = 0) -> list[tuple[int, list[int]]]:
    """(query row, its database rows) for every query of ``geoloc eval --folds`` (1: the manifest's split)."""
    sets = [[r.group for r in rows if r.split == "query"]] if folds <= 1 else assign_folds(rows, folds, seed)
    out = []
    for qgroups in sets:
        qset = set(qgroups)
        db = [i for i, r in enumerate(rows) if r.group not in qset and r.split != "train"]
        out += [(i, db) for i, r in enumerate(rows) if r.group in qset and r.split != "train"]
    return out


def _features(rows: list[Row], judge: Judge, workers: int, cache_dir: Path | None = None) -> list[Any]:
    """The judge's features of every row, each read from or written to its own file under
    ``cache_dir/<judge>/`` (named by the image's path, size and mtime: the 40-photo split's images are all
    in penn-campus-gps, so its features serve the 5 folds too)."""
    folder = None if cache_dir is None else cache_dir / judge.name.replace(":", "-")

    def one(r: Row) -> Any:
        st = r.image.stat()
        key = f"{r.image.resolve()}:{st.st_size}:{st.st_mtime_ns}"
        path = None if folder is None else folder / f"{hashlib.sha1(key.encode()).hexdigest()}.pkl"
        if path is not None and path.exists():
            return pickle.loads(path.read_bytes())
        f = judge.features(load_image(r.image.read_bytes()).rgb)
        if path is not None:
            folder.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(path, pickle.dumps(f, protocol=pickle.HIGHEST_PROTOCOL))
        return f

    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(one, rows))


def analyse(
    rows: list[Row],
    pairs: Sequence[tuple[int, list[int]]],
    judge: Judge,
    radius_m: float = 25.0,
    far_m: float = 100.0,
    far_per_query: int = 10,
    quantile: float = 1.0,
    workers: int = 2,
    seed: int = 0,
    max_near: int | None = None,
    cache_dir: Path | None = None,
) -> dict:
    """Per query: the most inliers with a reference within ``radius_m`` and whether that beats the far-pair
    threshold. Near references are tried nearest first (at most ``max_near``) and the search stops at the
    first that beats it."""
    t0 = time.perf_counter()
    used = sorted({q for q, _ in pairs} | {j for _, db in pairs for j in db})
    feats: list[Any] = [None] * len(rows)
    for i, f in zip(used, _features([rows[i] for i in used], judge, workers, cache_dir), strict=True):
        feats[i] = f
    t_features = time.perf_counter() - t0
    lat = np.array([r.lat for r in rows])
    lon = np.array([r.lon for r in rows])
    rng = np.random.default_rng(seed)
    far_inliers: list[int] = []
    far_pairs: list[tuple[int, int]] = []
    for q, db in pairs:
        d = haversine_m(lat[q], lon[q], lat[db], lon[db])
        far = [db[k] for k in np.flatnonzero(d > far_m)]
        chosen = [int(j) for j in rng.choice(far, min(far_per_query, len(far)), replace=False)] if far else []
        far_inliers += judge.inliers(feats[q], [feats[j] for j in chosen])
        far_pairs += [(q, j) for j in chosen]
    top = np.argsort(far_inliers)[::-1][:5]  # the pairs that set the threshold, to look at
    far_top = []
    for k in top:
        q, j = far_pairs[k]
        metres = float(haversine_m(lat[q], lon[q], lat[j], lon[j]))
        far_top.append(
            {
                "query": rows[q].image.name,
                "reference": rows[j].image.name,
                "distance_m": round(metres, 1),
                "inliers": int(far_inliers[k]),
            }
        )
    threshold = float(np.quantile(far_inliers, quantile)) if far_inliers else 0.0
    per_query = {}
    for q, db in pairs:
        d = haversine_m(lat[q], lon[q], lat[db], lon[db])
        near = [db[k] for k in np.argsort(d) if d[k] <= radius_m]
        best, tried = 0, 0
        for j in near[:max_near]:
            tried += 1
            best = max(best, judge.inliers(feats[q], [feats[j]])[0])
            if best > threshold:
                break
        per_query[q] = {"near": len(near), "tried": tried, "best_inliers": best, "verifiable": best > threshold}
    return {
        "judge": judge.name,
        "threshold_inliers": threshold,
        "far_pairs": len(far_inliers),
        "far_inliers_median": float(np.median(far_inliers)) if far_inliers else None,
        "far_inliers_quantiles": {
            str(p): float(np.quantile(far_inliers, p)) for p in (0.9, 0.99, 0.999) if far_inliers
        },
        "far_top": far_top,
        "quantile": quantile,
        "radius_m": radius_m,
        "far_m": far_m,
        "max_near": max_near,
        "seconds": time.perf_counter() - t0,
        "seconds_features": t_features,
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


def is_crop(row: Row) -> bool:
    """penn-campus-gps' 224 px crops live under ``crops/``; everything else is a whole photo."""
    return "crops" in row.image.parts


def summarise(rows: list[Row], result: dict, evals: Sequence[Path], radius_m: float) -> dict:
    """Share of verifiable queries and R@1 among them, for full photos and for crops (224 px) apart; each
    evaluation's misses split into "no verifiable shared view" (of which: no reference within the radius at
    all) and "a verifiable view exists, not found"."""
    kinds = {"photos": lambda r: not is_crop(r), "crops": is_crop}
    summary: dict = {}
    for kind, is_kind in kinds.items():
        qs = [q for q in result["per_query"] if is_kind(rows[q])]
        if not qs:
            continue
        pq = result["per_query"]
        ver = [q for q in qs if pq[q]["verifiable"]]
        entry: dict = {"queries": len(qs), "verifiable": len(ver), "share": len(ver) / max(len(qs), 1)}
        entry["no_reference_within_radius"] = sum(pq[q]["near"] == 0 for q in qs)
        entry["best_near_inliers_median"] = float(np.median([pq[q]["best_inliers"] for q in qs]))
        # Sensitivity to the threshold: verifiable at lower far-pair quantiles (exact, since a query stops
        # its search only above the threshold, which is above these).
        entry["verifiable_at_far_quantile"] = {
            p: sum(pq[q]["best_inliers"] > t for q in qs) for p, t in result.get("far_inliers_quantiles", {}).items()
        }
        for path in evals:
            hits = hits_at_1(rows, path, radius_m)

            def hit(q: int, hits: dict = hits) -> bool | None:
                return hits.get((rows[q].image.name, round(rows[q].lat, 7), round(rows[q].lon, 7)))

            def r1(sel: list[int]) -> float | None:
                got = [h for q in sel if (h := hit(q)) is not None]
                return float(np.mean(got)) if got else None

            missed = [q for q in qs if hit(q) is False]
            entry[path.name] = {
                "r1_all": r1(qs),
                "r1_verifiable": r1(ver),
                "r1_not_verifiable": r1([q for q in qs if q not in set(ver)]),
                "queries_in_eval": sum(hit(q) is not None for q in qs),
                "misses": len(missed),
                "misses_view_exists_not_found": sum(pq[q]["verifiable"] for q in missed),
                "misses_no_verifiable_view": sum(not pq[q]["verifiable"] for q in missed),
                "misses_no_reference_within_radius": sum(pq[q]["near"] == 0 for q in missed),
                "misses_view_exists_at_far_quantile": {
                    p: sum(pq[q]["best_inliers"] > t for q in missed)
                    for p, t in result.get("far_inliers_quantiles", {}).items()
                },
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
    ap.add_argument("--judge", default="sift-mnn", help=f"a matcher or stored profile: {', '.join(JUDGES)}")
    ap.add_argument("--models-dir", type=Path, default=Path("models"), help="where the judge's networks are")
    ap.add_argument(
        "--queries",
        choices=("all", "photos", "crops"),
        default="all",
        help="judge only these queries (and take the far-pair threshold from theirs alone)",
    )
    ap.add_argument("--sample", type=int, help="judge a random sample of this many of the queries (seed 0)")
    ap.add_argument("--cache-dir", type=Path, default=Path("out/cache/view-loss"), help="features, one file a photo")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--reuse", action="store_true", help="read the verification outcomes from --out again")
    ap.add_argument("--reuse-from", type=Path, help="read the verification outcomes from this output instead")
    ap.add_argument(
        "--union-with",
        type=Path,
        nargs="*",
        default=[],
        help="with --reuse(-from): other judges' outputs (same manifest "
        "and folds); a query is verifiable when any judge verifies it",
    )
    a = ap.parse_args(argv)
    rows = read_manifest(a.manifest)
    if a.reuse or a.reuse_from:  # only the R@1 split is recomputed (for other evaluations of the same queries)
        result = json.loads((a.reuse_from or a.out).read_text())
        result["per_query"] = {int(k.rsplit("@", 1)[1]): v for k, v in result["per_query"].items()}
        for other in a.union_with:
            theirs = json.loads(other.read_text())
            for k, v in theirs["per_query"].items():
                mine = result["per_query"].get(int(k.rsplit("@", 1)[1]))
                if mine is not None:
                    mine["verifiable"] = mine["verifiable"] or v["verifiable"]
            result["judge"] = f"{result['judge']} or {theirs['judge']}"
        if a.union_with:  # the thresholds and inlier counts are each judge's own: no sensitivity across them
            result.pop("far_inliers_quantiles", None)
    else:
        pairs = query_databases(rows, a.folds)
        if a.queries != "all":
            pairs = [(q, db) for q, db in pairs if is_crop(rows[q]) == (a.queries == "crops")]
        if a.sample is not None and a.sample < len(pairs):  # in manifest order, so folds stay mixed
            keep = np.random.default_rng(0).choice(len(pairs), a.sample, replace=False)
            pairs = [pairs[i] for i in sorted(keep)]
        judge = make_judge(a.judge, a.models_dir)
        result = analyse(
            rows,
            pairs,
            judge,
            a.radius_m,
            a.far_m,
            a.far_per_query,
            workers=a.workers,
            max_near=a.max_near,
            cache_dir=a.cache_dir,
        )
        result["queries"] = a.queries if a.sample is None else f"{a.queries}, a sample of {len(pairs)}"
    result["summary"] = summarise(rows, result, a.eval, a.radius_m)
    result["per_query"] = {rows[q].image.name + f"@{q}": v for q, v in result["per_query"].items()}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "per_query"}, indent=1))


if __name__ == "__main__":
    main()
