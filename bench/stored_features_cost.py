"""What storing local features costs at ingestion and on disk (issue 32): ``lite2-hybrid-384-sv`` against
``lite2-hybrid-384``, interleaved in one process.

    .venv/bin/python -m bench.stored_features_cost [--models-dir models] [--photos 16] [--crops 32] [--repeat 3]

Each repetition ingests the same penn images (1600 px whole photos, then 224 px crops) into a fresh data
dir per configuration, the two back to back, alternating which goes first so both see the same load. Timed:
``encode_and_complete`` on the local engine with one thread (decode, local features, CNN, aggregation and,
for ``-sv``, the XFeat record; then the writer: rows, codes and the feature files), what the worker and
`geoloc ingest` run; the upload's acceptance (row and image) is the same for both and not timed. Each
configuration's pipeline is loaded and warmed once, before the repetitions, so no side pays for loading
its models or onnxruntime's first run per input shape. Reported: median images/s per configuration and the
ratio (target >= 0.8x), and the bytes of the ``.lf`` files the ``-sv`` runs wrote (their sizes, and the
file system blocks they hold), with the load average before and after.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

# Before numpy and any session are loaded: one worker's thread, as bench/ingest_speed.py's local path.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from app.domain import Upload  # noqa: E402
from app.engine.models.ort import set_session_threads  # noqa: E402
from app.engine.pipeline import Pipeline  # noqa: E402
from app.ingestion.encoding.items import EncodeItem, encode_data  # noqa: E402
from app.ingestion.encoding.local import LocalEngine, encode_and_complete  # noqa: E402
from app.storage.feature_files import FeatureFiles, profile_root  # noqa: E402
from app.usecases.service import GeolocService  # noqa: E402
from bench.common import REPO, machine  # noqa: E402
from bench.ingest_speed import uploads  # noqa: E402

set_session_threads(1)

BASE, STORED = "lite2-hybrid-384", "lite2-hybrid-384-sv"
COMMAND = ".venv/bin/python -m bench.stored_features_cost"


def warm_pipeline(root: Path, models_dir: Path, config: str, images: list[Upload]) -> Pipeline:
    """The configuration's pipeline, loaded once and run on two images of each size."""
    service = GeolocService.open(Path(tempfile.mkdtemp(dir=root)), models_dir, config)
    for image in images:
        if encode_data(service.pipeline, service.limits, 0, image.data).error is not None:
            raise SystemExit(f"{config}: {image.filename} does not encode")
    service.store.close()
    return service.pipeline


def ingest_once(root: Path, models_dir: Path, config: str, pipeline: Pipeline, images: list[Upload]) -> tuple:
    """(images/s, data dir) of one ingestion of ``images`` into a fresh data dir."""
    data = Path(tempfile.mkdtemp(dir=root))
    service = GeolocService.open(data, models_dir, config)
    try:
        accepted = service.accept(images, source="bench")
        items = [EncodeItem(i, service.store.image_path(i)) for i in accepted.reference_ids]
        t0 = time.perf_counter()
        done = encode_and_complete(service, items, LocalEngine(pipeline, service.limits, 1), batch=32)
        seconds = time.perf_counter() - t0
    finally:
        service.store.close()
    if done != len(images):
        raise SystemExit(f"{config}: only {done} of {len(images)} images were indexed")
    return len(images) / seconds, data


def stored_bytes(data: Path, profile: str) -> tuple[list[int], int]:
    """The sizes of the data dir's ``.lf`` files, and the file system blocks they hold (bytes)."""
    files = FeatureFiles(profile_root(data, profile))
    stats = [files.path(sha).stat() for sha in files.names()]
    return [s.st_size for s in stats], sum(s.st_blocks * 512 for s in stats)


def measure(kind: str, images: list[Upload], models_dir: Path, repeat: int, root: Path, warm: dict) -> dict:
    rates: dict[str, list[float]] = {BASE: [], STORED: []}
    sizes, blocks = [], 0
    for rep in range(repeat):
        order = [BASE, STORED] if rep % 2 == 0 else [STORED, BASE]
        for config in order:
            rate, data = ingest_once(root, models_dir, config, warm[config], images)
            rates[config].append(rate)
            if config == STORED and rep == 0:
                sizes, blocks = stored_bytes(data, warm[config].config.stored_features)
            shutil.rmtree(data, ignore_errors=True)
            print(f"  {kind} rep {rep + 1} {config}: {rate:.2f} images/s", flush=True)
    med = {c: statistics.median(r) for c, r in rates.items()}
    paired = [s / b for s, b in zip(rates[STORED], rates[BASE], strict=True)]  # each repetition's own ratio
    return {"kind": kind, "n": len(images), "rates": med, "ratio": med[STORED] / med[BASE], "paired": paired,
            "sizes": sizes, "blocks": blocks}  # fmt: skip


def cost_split(pipeline: Pipeline, images: list[Upload], root: Path) -> dict[str, float]:
    """Median ms per 1600 px photo and stage on the warm ``-sv`` pipeline, one image at a time: what the
    stored features add (the XFeat record, its bytes and file) against what both configurations pay."""
    from app.engine.imageio import ImageLimits
    from app.engine.stored_features import encode

    limits, files = ImageLimits().stored(), FeatureFiles(root / "split")
    per: dict[str, list[float]] = {"decode": [], "global + codes": [], "XFeat record": [], "bytes + file": []}
    for image in images:
        t0 = time.perf_counter()
        img = pipeline.decode(image.data, limits)
        t1 = time.perf_counter()
        pipeline.encode_image(img.rgb)
        t2 = time.perf_counter()
        record = pipeline.stored_extractor.record(img.rgb)
        t3 = time.perf_counter()
        files.write(f"{len(per['decode']):064x}", encode(record))
        t4 = time.perf_counter()
        for stage, t in zip(per, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
            per[stage].append(t * 1000)
    return {stage: statistics.median(v) for stage, v in per.items()}


def render(results: list[dict], args, load: tuple[float, float]) -> str:
    L = [
        f"`{COMMAND} --photos {args.photos} --crops {args.crops} --repeat {args.repeat} --split {args.split}` "
        f"({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {machine()}); load average (1 min) "
        f"{load[0]:.1f} before, {load[1]:.1f} after. Medians over {args.repeat} interleaved repetitions, one "
        "thread (onnxruntime, BLAS), encode + write (rows, codes, and the `.lf` files for -sv).",
        "",
        f"| images | n | {BASE} images/s | {STORED} images/s | ratio of medians (target >= 0.8x) | "
        "per-repetition ratio: median (min-max) | bytes per reference (median, max) | on disk per reference "
        "(blocks) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        s = sorted(r["sizes"])
        size = f"{statistics.median(s):,.0f} B ({statistics.median(s) / 1024:.1f} KB), {s[-1]:,} B" if s else "-"
        disk = f"{r['blocks'] / len(s) / 1024:.1f} KB" if s else "-"
        L.append(
            f"| {r['kind']} | {r['n']} | {r['rates'][BASE]:.2f} | {r['rates'][STORED]:.2f} | {r['ratio']:.2f}x "
            f"| {statistics.median(r['paired']):.2f}x ({min(r['paired']):.2f}-{max(r['paired']):.2f}) | {size} "
            f"| {disk} |"
        )
    if args.split_figures:
        split = args.split_figures
        added = split["XFeat record"] + split["bytes + file"]
        both = split["decode"] + split["global + codes"]
        L += [
            "",
            f"Per 1600 px photo, median ms, one at a time on the warm `{STORED}` pipeline ({len(args.split_set)} "
            "photos): " + ", ".join(f"{k} {v:.0f}" for k, v in split.items())
            + f". Stored features add {added:.0f} ms to {both:.0f} ms: {both / (both + added):.2f}x by these times.",
        ]  # fmt: skip
    return "\n".join(L)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--photos", type=int, default=16, help="1600 px photos per run (0: skip)")
    ap.add_argument("--crops", type=int, default=32, help="224 px crops per run (0: skip)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--split", type=int, default=8, help="photos timed stage by stage (0: none)")
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    root = Path(tempfile.mkdtemp(prefix="geoloc-stored-cost-"))
    try:
        sets = [(kind, uploads(kind, n)) for kind, n in (("photos", args.photos), ("crops", args.crops)) if n > 0]
        sample = [images[0] for _, images in sets] + [images[-1] for _, images in sets]
        warm = {c: warm_pipeline(root, args.models_dir, c, sample) for c in (BASE, STORED)}
        results = [measure(kind, images, args.models_dir, args.repeat, root, warm) for kind, images in sets]
        args.split_set = [images for kind, images in sets if kind == "photos"][:1]
        args.split_set = args.split_set[0][: args.split] if args.split_set and args.split else []
        args.split_figures = cost_split(warm[STORED], args.split_set, root) if args.split_set else None
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(render(results, args, (load0, os.getloadavg()[0])))


if __name__ == "__main__":
    main()
