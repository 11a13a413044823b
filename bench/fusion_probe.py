"""Would two descriptors searched together beat either alone? A probe before building a configuration.

Late fusion of two named configurations: each is fitted per fold exactly as ``geoloc eval`` fits it (its
own codebook, PCA-whitening on the fold's db and train rows), its float codes (unit length) are scaled by
sqrt(w) and sqrt(1 - w) and joined, so one inner-product search of the joined codes ranks by
``w * score_a + (1 - w) * score_b``. That is what a configuration with two global branches would serve
from one flat index. Recall@N within 25 m over the same folds as the evaluation, for a grid of w
(w = 1: config A alone, w = 0: B alone, which must equal their ``geoloc eval`` rows: the check that this
probe measures what the evaluation measures).

    python -m bench.fusion_probe --manifest data/manifests/penn-campus-gps.csv --a hybrid --b lite2-mid-gem \
        --folds 5 --models-dir models --cache out/cache

Not a service path: the SVM bank is off (as the evaluation's default) and there is no estimate, only the
ranking.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
from pathlib import Path

import numpy as np

from app.engine.artifacts import atomic_write_bytes
from app.engine.configs import PipelineConfig, get_config
from app.engine.geo import haversine_m
from app.engine.pipeline import Pipeline
from app.evaluation.datasets import read_manifest
from app.evaluation.evaluate import RECALL_AT, assign_folds, extract_cached


def fold_codes(config: PipelineConfig, rows, cache: Path | None, models_dir: Path, query_sets, seed: int):
    """Per fold: (query codes, db codes, query indices, db indices) of one configuration; kept in the cache
    folder, keyed by the definition, the folds, the seed, the images (path, size, mtime) and the built
    models, since fitting is most of a probe's time."""
    if cache is not None:
        key = hashlib.sha256(f"{config.model_dump_json()}-{seed}-{json.dumps(query_sets)}".encode())
        for p in [r.image for r in rows] + sorted(models_dir.glob("*.onnx")):
            st = p.stat()
            key.update(f"{p}:{st.st_size}:{st.st_mtime_ns}".encode())
        path = cache / f"fold-codes-{key.hexdigest()[:20]}.pkl"
        if path.exists():
            return pickle.loads(path.read_bytes())
        out = _fold_codes(config, rows, cache, models_dir, query_sets, seed)
        atomic_write_bytes(path, pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL))
        return out
    return _fold_codes(config, rows, cache, models_dir, query_sets, seed)


def _fold_codes(config: PipelineConfig, rows, cache: Path | None, models_dir: Path, query_sets, seed: int):
    base = Pipeline(config, models_dir=models_dir)
    extracted = extract_cached(base, rows, cache)
    out = []
    for f, qgroups in enumerate(query_sets):
        qset = set(qgroups)
        q_idx = [i for i, r in enumerate(rows) if r.group in qset and r.split != "train"]
        db_idx = [i for i, r in enumerate(rows) if r.group not in qset and r.split != "train"]
        fit_idx = db_idx + [i for i, r in enumerate(rows) if r.split == "train"]
        pipe = Pipeline(config, base.global_model, models_dir=models_dir)
        pipe.fit([extracted[i].features for i in fit_idx], seed=seed + f)

        q_codes, db_codes = (
            np.stack([pipe.encode_features(extracted[i].features).float_ for i in idx]) for idx in (q_idx, db_idx)
        )
        out.append((q_codes, db_codes, q_idx, db_idx))
    return out


def recall(rows, q_idx, db_idx, scores: np.ndarray, radius_m: float) -> np.ndarray:
    """Per query, hit at each N of RECALL_AT."""
    lat = np.array([rows[i].lat for i in db_idx])
    lon = np.array([rows[i].lon for i in db_idx])
    order = np.argsort(-scores, axis=1)[:, : max(RECALL_AT)]
    hits = np.zeros((len(q_idx), len(RECALL_AT)), bool)
    for qi, i in enumerate(q_idx):
        d = haversine_m(rows[i].lat, rows[i].lon, lat[order[qi]], lon[order[qi]])
        for j, n in enumerate(RECALL_AT):
            hits[qi, j] = np.any(d[:n] <= radius_m)
    return hits


def expand(x: np.ndarray, d: np.ndarray, k: int, alpha: float, skip_self: bool = False) -> np.ndarray:
    """alpha-weighted query expansion (Radenovic et al.): each row of ``x`` plus its top ``k`` rows of ``d``
    weighted by score^alpha, re-normalised; with ``skip_self`` (database-side augmentation) a row's own
    entry is not among its neighbours."""
    s = x @ d.T
    if skip_self:
        np.fill_diagonal(s, -np.inf)
    top = np.argsort(-s, axis=1)[:, :k]
    wts = np.clip(np.take_along_axis(s, top, axis=1), 0, None) ** alpha
    out = x + np.einsum("nk,nkd->nd", wts, d[top])
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--manifest", type=Path, required=True)
    ap.add_argument("--a", required=True, help="configuration A (weight w)")
    ap.add_argument("--b", required=True, help="configuration B (weight 1 - w)")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--radius", type=float, default=25.0)
    ap.add_argument("--models-dir", type=Path, default=Path("models"))
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--weights", default="1,0.8,0.7,0.6,0.5,0.4,0.3,0.2,0")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--qe", type=int, default=0, help="alpha query expansion with the top K (0: none)")
    ap.add_argument("--dba", type=int, default=0, help="database-side augmentation with the top K (0: none)")
    ap.add_argument("--alpha", type=float, default=3.0)
    ap.add_argument("--set-a", action="append", default=[], metavar="FIELD=VALUE", help="override A's settings")
    ap.add_argument("--set-b", action="append", default=[], metavar="FIELD=VALUE", help="override B's settings")
    args = ap.parse_args(argv)

    weights = [float(x) for x in args.weights.split(",")]
    if not all(0 <= w <= 1 for w in weights):
        ap.error(f"--weights are shares of configuration A, between 0 and 1: {args.weights}")
    rows = read_manifest(args.manifest)
    query_sets = assign_folds(rows, args.folds, args.seed)
    config_a = get_config(args.a).with_overrides(dict(kv.split("=", 1) for kv in args.set_a))
    config_b = get_config(args.b).with_overrides(dict(kv.split("=", 1) for kv in args.set_b))
    a = fold_codes(config_a, rows, args.cache, args.models_dir, query_sets, args.seed)
    b = a if config_b == config_a else fold_codes(config_b, rows, args.cache, args.models_dir, query_sets, args.seed)
    report = {"a": config_a.name, "b": config_b.name, "folds": args.folds, "qe": args.qe, "dba": args.dba, "rows": []}
    print(f"w * {config_a.name} + (1 - w) * {config_b.name}, {args.folds} folds (mean), qe {args.qe}, dba {args.dba}")
    print("w     " + "  ".join(f"R@{n:<4}" for n in RECALL_AT))
    for w in weights:
        per_fold = []
        for (qa, da, q_idx, db_idx), (qb, db, q_idx_b, db_idx_b) in zip(a, b, strict=True):
            assert q_idx == q_idx_b and db_idx == db_idx_b
            q = np.hstack([np.sqrt(w) * qa, np.sqrt(1 - w) * qb])
            d = np.hstack([np.sqrt(w) * da, np.sqrt(1 - w) * db])
            if args.dba:
                d = expand(d, d, args.dba, args.alpha, skip_self=True)
            if args.qe:
                q = expand(q, d, args.qe, args.alpha)
            per_fold.append(recall(rows, q_idx, db_idx, q @ d.T, args.radius).mean(axis=0))
        mean = np.mean(per_fold, axis=0)
        recall_at = dict(zip(map(str, RECALL_AT), mean.tolist(), strict=True))
        report["rows"].append({"w": w, "recall_at": recall_at, "per_fold": np.array(per_fold).tolist()})
        print(f"{w:<5} " + "  ".join(f"{x:.3f} " for x in mean))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
