"""How many references a collection needs before its own calibration can give a confident answer.

    python -m bench.calibration_size [--manifest data/manifests/penn-campus-gps.csv] [--sizes 20,40,...]
                                     [--seeds 3] [--first-seed 0]

Why: `geoloc refit` of a 20-photo collection found no level at which its answers held (threshold 1.01), and
nothing told the user that this is the collection's size, not a fault. This refits, as `geoloc
refit` does (fit, SVM bank and calibration on the references alone), seeded subsets of whole captures of the
manifest's db rows of increasing size, and prints per size and seed whether the calibration found a
confident level. ``app.engine.calibration.CONFIDENT_FROM_REFERENCES`` is the size from which every seed did.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from app.engine.configs import DEFAULT_CONFIG, get_config
from app.engine.pipeline import Pipeline
from app.evaluation.evaluate import extract_cached
from app.manifests import read_manifest
from app.settings import REPO_ROOT
from app.usecases.fitting import FitOptions, FitPhoto, bank_source, fit_pipeline


def subset(groups: dict[str, list[int]], size: int, seed: int) -> list[int]:
    """Whole captures in a seeded order until ``size`` references are taken."""
    names = sorted(groups)
    np.random.default_rng(seed).shuffle(names)
    out: list[int] = []
    for g in names:
        if len(out) >= size:
            break
        out += groups[g]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--manifest", type=Path, default=REPO_ROOT / "data/manifests/penn-campus-gps.csv")
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--models-dir", type=Path, default=REPO_ROOT / "models")
    ap.add_argument("--sizes", default="20,40,60,80,120,160,240,389")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=REPO_ROOT / "out/cache")
    args = ap.parse_args()
    cfg = get_config(args.config)
    rows = [r for r in read_manifest(args.manifest) if r.split == "db"]
    pipe = Pipeline(cfg, models_dir=args.models_dir)
    pipe.load_models()
    feats = [e.features for e in extract_cached(pipe, rows, args.cache)]
    groups: dict[str, list[int]] = {}
    for i, r in enumerate(rows):
        groups.setdefault(r.group, []).append(i)
    print(f"{len(rows)} db rows in {len(groups)} captures ({cfg.name})")
    print("references  seed  confident_p  calibration")
    for size in (int(s) for s in args.sizes.split(",")):
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            ids = subset(groups, size, seed)
            photos = [FitPhoto(rows[i].image, feats[i], rows[i].lat, rows[i].lon, rows[i].group, ref_id=i) for i in ids]
            t0 = time.perf_counter()
            fitted = Pipeline(cfg, pipe.global_model, models_dir=args.models_dir)
            # A subset too uniform for a bank is fitted without one, as the first start does.
            fit = fit_pipeline(fitted, photos, FitOptions(bank=bank_source(cfg, None), bank_optional=True, seed=seed))
            if fit.bank == "none" and fitted.config.svm_bank:
                print("  (no SVM bank)")
            cal = fitted.calibration
            cp = cal.confident_p if cal.calibrated else None
            print(
                f"{len(ids):10d}  {seed:4d}  {'-' if cp is None else f'{cp:.3f}':>11}  {cal.source}: {cal.note} "
                f"({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
