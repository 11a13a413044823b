"""Photos of places a collection does not hold, located against it: how many get a confident estimate.

    .venv/bin/python -m bench.absent_places [--data-dir index] [--models-dir models] [--config hybrid] \
        [PHOTO_OR_FOLDER ...]   # default: every sf-streetview-toy image (22 San Francisco streets)

Why: "Not in this collection" must be an answer. The sf-streetview-toy images are street views of
San Francisco; against the Penn demo collection (`make demo`) none is present, so every confident estimate
is a wrong answer. Each photo goes through ``GeolocService.locate``, the use case /locate serves. Prints one
line per photo (reason code, best p_within_25m) and the summary: confident share, mean and highest best p.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from app.domain import LocateOptions
from app.engine.configs import DEFAULT_CONFIG
from app.usecases.service import GeolocService

REPO = Path(__file__).resolve().parents[1]
SF = REPO.parent / "shared" / "data" / "sf-streetview-toy"


def photos(args: list[str]) -> list[Path]:
    paths = [Path(a) for a in args] or [SF / "database", SF / "queries"]
    out = []
    for p in paths:
        out += sorted(p.glob("*.jpg")) if p.is_dir() else [p]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", nargs="*")
    ap.add_argument("--data-dir", type=Path, default=REPO / "index")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    args = ap.parse_args()
    service = GeolocService.open(args.data_dir, args.models_dir, args.config)
    confident, best = [], []
    for path in photos(args.photos):
        a = service.locate(path.read_bytes(), LocateOptions(top_k=10))
        p = max((c.p_within_25m for c in a.candidates if c.p_within_25m is not None), default=None)
        confident.append(a.reason is None)
        best.append(p if p is not None else float("nan"))
        shown = "n/a" if p is None else f"{p:.3f}"
        print(f"{path.parent.name}/{path.name}: {a.reason_code or 'CONFIDENT'}  best p_within_25m {shown}")
    print(
        f"{len(confident)} photos against {args.data_dir} ({service.collection.view().index.size} references): "
        f"{sum(confident)} confident ({np.mean(confident):.0%}), best p_within_25m mean {np.nanmean(best):.3f}, "
        f"highest {np.nanmax(best):.3f}"
    )


if __name__ == "__main__":
    main()
