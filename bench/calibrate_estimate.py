"""Choose the fused estimate's temperature and confidence threshold on the *train* rows (never on queries).

    .venv/bin/python bench/calibrate_estimate.py --manifest data/manifests/penn-campus-gps.csv --config hybrid

The pipeline is fitted on db + train rows, each train row is located against the db rows, and for a grid
of (temperature, min_confidence) we measure how often a confident estimate lies within the radius
(precision) and how often the estimate is confident at all (coverage). We keep the setting with the best
coverage among those whose precision reaches the target; the evaluation then reports the same figures on
the query rows, which the choice never saw.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from app.datasets import read_manifest
from app.engine.cnn import MODEL_FILENAME, SqueezeNet
from app.engine.configs import get_config
from app.engine.estimate import fuse_position
from app.engine.geo import haversine_m
from app.engine.pipeline import Pipeline
from app.engine.search import ReferenceIndex
from app.evaluate import extract_cached

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--manifest", type=Path, default=REPO / "data/manifests/penn-campus-gps.csv")
    ap.add_argument("--config", default="hybrid")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--cache", type=Path, default=REPO / "out/eval/cache")
    ap.add_argument("--radius-m", type=float, default=25.0)
    ap.add_argument("--target-precision", type=float, default=0.6)
    args = ap.parse_args()

    rows = read_manifest(args.manifest)
    cfg = get_config(args.config)
    cnn = SqueezeNet(args.models_dir / MODEL_FILENAME) if cfg.uses_cnn else None
    ex = extract_cached(Pipeline(cfg, cnn), rows, args.cache, workers=1)
    db = [i for i, r in enumerate(rows) if r.split == "db"]
    train = [i for i, r in enumerate(rows) if r.split == "train"]
    pipe = Pipeline(cfg, cnn)
    pipe.fit([ex[i].features for i in db + train])
    index = ReferenceIndex(cfg, pipe.float_dim, pipe.bits)
    codes = [pipe.encode_features(ex[i].features) for i in db]
    index.add(
        np.array(db),
        np.stack([c.float_ for c in codes]) if pipe.float_dim else None,
        np.stack([c.binary for c in codes]) if pipe.bits else None,
    )
    lat = np.array([r.lat for r in rows])
    lon = np.array([r.lon for r in rows])
    cands = []
    for i in train:
        c = pipe.encode_features(ex[i].features)
        s, ids = index.search(c.float_, c.binary, 20)
        cands.append((i, lat[ids], lon[ids], s))

    print(f"{len(train)} train queries against {len(db)} references; radius {args.radius_m} m")
    print("temperature  min_conf  coverage  precision")
    best = None
    for temp in (0.005, 0.01, 0.02, 0.04):
        confs, oks = [], []
        for i, la, lo, s in cands:
            e = fuse_position(la, lo, s, args.radius_m, temperature=temp, min_confidence=0.0)
            confs.append(e.confidence)
            oks.append(haversine_m(lat[i], lon[i], e.lat, e.lon) <= args.radius_m)
        confs, oks = np.array(confs), np.array(oks)
        for thr in (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9):
            sel = confs >= thr
            cov = sel.mean()
            prec = oks[sel].mean() if sel.any() else float("nan")
            print(f"{temp:11.3f}  {thr:8.2f}  {cov:8.2f}  {prec:9.2f}")
            if sel.sum() >= 5 and prec >= args.target_precision and (best is None or cov > best[2]):
                best = (temp, thr, cov, prec)
    print("all estimates within radius:", f"{np.mean(oks):.2f}")
    print("chosen (best coverage at precision >= target):", best)


if __name__ == "__main__":
    main()
