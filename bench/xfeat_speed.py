"""XFeat against RootSIFT as the local-feature stage, timed interleaved image by image in one process.

Why interleaved: this machine is shared and its load changes by the minute; timing one extractor over
all photos and then the other would compare two different machines. Here each photo is decoded once and
both extractors run on it back to back, in alternating order, with the settings the configurations use
(``hybrid``: RootSIFT, 1,000 keypoints at 640 px; ``hybrid-xfeat``: XFeat at the same size). With
``--extract`` the whole extraction stage (local features + SqueezeNet + the hybrid sampling) of both
configurations is timed the same way. Prints medians and the XFeat / RootSIFT ratio.

    python -m bench.xfeat_speed [--photos ../shared/data/penn-campus-gps/photos] [--repeat 2] [--extract]
                                [--set max_keypoints=2048] [--set local_long_side=480]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from app.engine.configs import get_config
from app.engine.imageio import load_image
from app.engine.models.ort import set_session_threads
from app.engine.pipeline import Pipeline
from app.engine.registry import Kind, create
from app.settings import Settings
from bench.common import REPO, median_ms


def _timed(fn, rgb) -> float:
    t0 = time.perf_counter()
    fn(rgb)
    return (time.perf_counter() - t0) * 1000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=Path, default=REPO.parent / "shared" / "data" / "penn-campus-gps" / "photos")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--limit", type=int, default=0, help="first N photos (0: all)")
    ap.add_argument("--repeat", type=int, default=2, help="timed runs per photo and extractor")
    ap.add_argument("--extract", action="store_true", help="also time Pipeline.extract of both configurations")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="vary hybrid-xfeat: k=v")
    args = ap.parse_args()
    settings = Settings()
    set_session_threads(settings.ort_threads)

    overrides = dict(o.split("=", 1) for o in args.overrides)
    sift_cfg, xfeat_cfg = get_config("hybrid"), get_config("hybrid-xfeat").with_overrides(overrides)
    stages = {
        "rootsift": create(
            Kind.LOCAL_EXTRACTOR, "sift", max_keypoints=sift_cfg.max_keypoints, long_side=sift_cfg.local_long_side
        ),
        "xfeat": create(
            Kind.LOCAL_EXTRACTOR,
            "xfeat",
            args.models_dir,
            max_keypoints=xfeat_cfg.max_keypoints,
            long_side=xfeat_cfg.local_long_side,
        ),
    }
    if args.extract:
        hybrid = Pipeline(sift_cfg, models_dir=args.models_dir)
        stages["extract hybrid"] = hybrid.extract
        stages["extract hybrid-xfeat"] = Pipeline(xfeat_cfg, hybrid.global_model, models_dir=args.models_dir).extract
    photos = sorted(args.photos.glob("*.jpg"))[: args.limit or None]
    rgbs = [load_image(p.read_bytes()).rgb for p in photos]
    for fn in stages.values():  # warm-up: sessions, allocator, caches
        fn(rgbs[0])
    times: dict[str, list[float]] = {k: [] for k in stages}
    names = list(stages)
    for i, rgb in enumerate(rgbs):
        for r in range(args.repeat):
            order = names if (i + r) % 2 == 0 else names[::-1]
            for name in order:
                times[name].append(_timed(stages[name], rgb))
    h, w = rgbs[0].shape[:2]
    print(
        f"{len(rgbs)} photos ({w}x{h} px first), {args.repeat} runs each, interleaved; "
        f"{xfeat_cfg.name}; onnxruntime threads {settings.ort_threads or 'all cores'} (GEOLOC_ORT_THREADS), "
        f"{os.cpu_count()} cores"
    )
    med = {k: median_ms(v) for k, v in times.items()}
    for k, v in med.items():
        print(f"  {k:22s} median {v:7.1f} ms")
    print(f"  local features: XFeat / RootSIFT = {med['xfeat'] / med['rootsift']:.2f}")
    if args.extract:
        print(f"  extraction: hybrid-xfeat / hybrid = {med['extract hybrid-xfeat'] / med['extract hybrid']:.2f}")


if __name__ == "__main__":
    main()
