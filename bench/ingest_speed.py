"""Ingestion speed: images/s of the local path and of Ray on 1 and 2 workers, the writer's share, the
per-image cost split, and what that projects for 1,000,000 images on a cluster.

Why in one process, interleaved: this machine is shared and its load changes by the minute, so every
repetition runs the three engines back to back on fresh data dirs holding the same images, and the
figures are medians over repetitions with ratios against the local path measured alongside. A worker is
1 CPU with onnxruntime and OpenCV on 1 thread (the local path too: one onnxruntime thread, ``set_session_threads(1)``).
Pool start-up (loading the models in each actor) is timed apart from images/s.

    .venv/bin/python -m bench.ingest_speed [--models-dir models] [--config hybrid] [--photos 24]
        [--crops 64] [--repeat 3] [--write-docs]

The per-image split times the real functions one image at a time: read (``Path.read_bytes``), decode
(``load_image``), features (the local-feature extractor and the hybrid sampling), CNN (SqueezeNet),
aggregation (VLAD, PCA, binary codes) and insert (``GeolocService.complete`` of a batch, per image).
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

# Before numpy and any session are loaded: the local path is one worker too (1 CPU), as Ray's actors are
# (Ray sets OMP_NUM_THREADS to the CPUs an actor holds; BLAS would otherwise spin on both cores here).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import cv2  # noqa: E402

from app.domain import Upload  # noqa: E402
from app.engine.configs import DEFAULT_CONFIG  # noqa: E402
from app.engine.imageio import load_image  # noqa: E402
from app.engine.models.ort import set_session_threads  # noqa: E402
from app.ingestion.completion import complete  # noqa: E402
from app.ingestion.encoding.items import Encoded, EncodeItem  # noqa: E402
from app.ingestion.encoding.local import LocalEngine, encode_and_complete  # noqa: E402
from app.usecases.service import GeolocService  # noqa: E402
from bench.common import REPO, write_section  # noqa: E402

set_session_threads(1)  # before any session: one onnxruntime thread, as an actor holding 1 CPU
PENN = REPO.parent / "shared" / "data" / "penn-campus-gps"
DOC = REPO / "docs" / "benchmarks.md"
STAGES = ("read", "decode", "features", "cnn", "aggregation", "insert")


def uploads(kind: str, n: int) -> list[Upload]:
    """``n`` real penn images with their positions: 1600 px photos or 224 px crops (one per capture first)."""
    with (PENN / "index.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    if kind == "photos":
        paths = [(r["photo"], r) for r in rows if r["photo"]]
    else:
        paths = [(c, r) for k in range(5) for r in rows for c in r["crops"].split(";")[k : k + 1]]
    if n > len(paths):
        raise SystemExit(f"--{kind} {n}: only {len(paths)} {kind} in {PENN}")
    return [Upload((PENN / p).read_bytes(), Path(p).name, float(r["lat"]), float(r["lon"])) for p, r in paths[:n]]


class TimedWriter:
    """``complete`` as ``encode_and_complete`` calls it, with the time spent completing (the writer) summed."""

    def __init__(self) -> None:
        self.seconds = 0.0

    def __call__(self, service: GeolocService, results: Sequence[Encoded]) -> list[int]:
        t0 = time.perf_counter()
        try:
            return complete(service, results)
        finally:
            self.seconds += time.perf_counter() - t0


def fresh(root: Path, models_dir: Path, config: str, images: list[Upload]) -> tuple[GeolocService, list[EncodeItem]]:
    data = Path(tempfile.mkdtemp(dir=root))
    service = GeolocService.open(data, models_dir, config)
    service.accept(images, source="bench")
    return service, [EncodeItem(i, p) for i, p in service.store.pending(len(images) + 1)]


def timed_run(service: GeolocService, items: list[EncodeItem], engine) -> tuple[float, float, float]:
    """(images/s, writer share, CPU ms per image) of one ``encode_and_complete`` over ``items``. CPU time is
    this process's (driver, writer, local threads) plus the Ray actors': what an image costs whatever the
    load, so it tells Ray's overhead apart from the shared machine's noise."""
    writer = TimedWriter()
    actors_cpu = getattr(engine, "cpu_seconds", lambda: 0.0)
    c0, a0 = time.process_time(), actors_cpu()
    t0 = time.perf_counter()
    done = encode_and_complete(service, items, engine, batch=32, complete_batch=writer)
    total = time.perf_counter() - t0
    cpu = time.process_time() - c0 + actors_cpu() - a0
    if done != len(items):
        raise SystemExit(f"only {done} of {len(items)} rows were completed")
    return len(items) / total, writer.seconds / total, cpu * 1000 / len(items)


def cost_split(service: GeolocService, items: list[EncodeItem]) -> dict[str, float]:
    """Median ms per image and stage, one image at a time on this thread."""
    pipe, per = service.pipeline, {s: [] for s in STAGES}
    results = []
    for item in items:
        t0 = time.perf_counter()
        data = item.path.read_bytes()
        t1 = time.perf_counter()
        rgb = load_image(data, service.limits).rgb
        t2 = time.perf_counter()
        f = pipe.extract(rgb)
        codes = pipe.encode_features(f)
        t = codes.timings_ms
        per["read"].append((t1 - t0) * 1000)
        per["decode"].append((t2 - t1) * 1000)
        per["features"].append(t.get("local_features", 0.0) + t.get("hybrid", 0.0))
        per["cnn"].append(t.get("cnn", 0.0))
        per["aggregation"].append(t.get("aggregate", 0.0) + t.get("codes", 0.0))
        results.append(Encoded(item.ref_id, codes.float_, codes.binary))
    for start in range(0, len(results), 32):
        chunk = results[start : start + 32]
        t0 = time.perf_counter()
        complete(service, chunk)
        per["insert"] += [(time.perf_counter() - t0) * 1000 / len(chunk)] * len(chunk)
    return {s: statistics.median(v) for s, v in per.items()}


def measure(kind: str, n: int, args, root: Path) -> dict:
    from app.ingestion.encoding.ray import RayEngine

    images = uploads(kind, n)
    service, items = fresh(root, args.models_dir, args.config, images)
    cost_split(service, items[:2])  # warm-up: sessions, caches
    split = cost_split(service, (items[2:] or items)[: args.split_images])  # past the warm-up when there are enough
    variants = {"local": None, **{f"ray {w}": w for w in args.workers}}
    speed: dict[str, list[float]] = {v: [] for v in variants}
    share: dict[str, list[float]] = {v: [] for v in variants}
    cpu: dict[str, list[float]] = {v: [] for v in variants}
    start_s: list[float] = []
    for rep in range(args.repeat):
        for name, workers in variants.items():
            service, items = fresh(root, args.models_dir, args.config, images)
            t0 = time.perf_counter()
            if workers is None:
                engine = LocalEngine(service.pipeline, service.limits, 1)
            else:
                engine = RayEngine(service.pipeline.source, service.limits, address="local", workers=workers)
                start_s.append(time.perf_counter() - t0)
            try:
                ips, ws, cpu_ms = timed_run(service, items, engine)
            finally:
                engine.close()
                service.store.close()
            speed[name].append(ips)
            share[name].append(ws)
            cpu[name].append(cpu_ms)
            print(
                f"  {kind} rep {rep + 1} {name}: {ips:.2f} img/s, writer {ws:.1%}, {cpu_ms:.0f} CPU ms/img", flush=True
            )
    med = {v: statistics.median(s) for v, s in speed.items()}
    return {
        "kind": kind,
        "n": n,
        "split": split,
        "speed": med,
        "writer": {v: statistics.median(s) for v, s in share.items()},
        "cpu_ms": {v: statistics.median(s) for v, s in cpu.items()},
        "pool_start_s": statistics.median(start_s) if start_s else float("nan"),
    }


def projection(split: dict[str, float], efficiency: float, cores: Sequence[int], nodes: int = 16) -> list[str]:
    """Hours for 10^6 images on ``nodes`` x N cores: encoding spread over the cores (at the measured
    scaling efficiency), while reading and inserting stay on the one driver (serial)."""
    encode_ms = sum(split[s] for s in ("decode", "features", "cnn", "aggregation"))
    driver_ms = split["read"] + split["insert"]
    lines = []
    for n in cores:
        encode_h = 1e6 * encode_ms / 1000 / (nodes * n * max(efficiency, 1e-9)) / 3600
        driver_h = 1e6 * driver_ms / 1000 / 3600
        lines.append(
            f"| {nodes} x {n} = {nodes * n} | {encode_h:.2f} | {driver_h:.2f} | {max(encode_h, driver_h):.2f} |"
        )
    return lines


def report(results: list[dict], args, load: tuple[float, float]) -> str:
    import ray

    ray_version, w = ray.__version__, args.workers
    lines = [
        f"Command: `.venv/bin/python -m bench.ingest_speed --photos {args.photos} --crops {args.crops} "
        f"--repeat {args.repeat}` (config {args.config}, Ray {ray_version}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores); "
        f"load average {load[0]:.1f} before, {load[1]:.1f} after. "
        f"Medians over {args.repeat} interleaved repetitions.",
        "",
        "| images | n | local img/s | " + " | ".join(f"Ray {k} img/s (vs local)" for k in w)
        + " | 2 vs 1 worker (efficiency) | writer share (local / Ray max) | pool start |",
        "|---|---|---|" + "---|" * len(w) + "---|---|---|",
    ]  # fmt: skip
    for r in results:
        s = r["speed"]
        ray_cells = " | ".join(f"{s[f'ray {k}']:.2f} ({s[f'ray {k}'] / s['local']:.2f}x)" for k in w)
        up = s.get("ray 2", float("nan")) / s.get("ray 1", float("nan"))
        writer = f"{r['writer']['local']:.1%} / {r['writer'][f'ray {max(w)}']:.1%}"
        lines.append(
            f"| {r['kind']} | {r['n']} | {s['local']:.2f} | {ray_cells} | {up:.2f}x ({up / 2:.0%}) | {writer} "
            f"| {r['pool_start_s']:.1f} s |"
        )
    lines += [
        "",
        "CPU ms per image (driver + writer + actors; independent of the load; ratio vs local):",
        "",
        "| images | " + " | ".join(results[0]["cpu_ms"]) + " |",
        "|---|" + "---|" * len(results[0]["cpu_ms"]) if results else "",
    ]
    for r in results:
        c = r["cpu_ms"]
        lines.append(f"| {r['kind']} | " + " | ".join(f"{v:.0f} ({v / c['local']:.2f}x)" for v in c.values()) + " |")
    lines += ["", "Per-image cost (median ms, one thread):", ""]
    lines += ["| images | " + " | ".join(STAGES) + " | total |", "|---|" + "---|" * (len(STAGES) + 1)]
    for r in results:
        sp = r["split"]
        lines.append(f"| {r['kind']} | " + " | ".join(f"{sp[s]:.1f}" for s in STAGES) + f" | {sum(sp.values()):.1f} |")
    for r in results:
        s = r["speed"]
        eff = s.get("ray 2", float("nan")) / s.get("ray 1", float("nan")) / 2
        lines += [
            "",
            f"Projection for 1,000,000 {r['kind']} on 16 nodes of N cores (hours; encoding at the measured "
            f"efficiency {eff:.0%}, read + insert serial on the one driver):",
            "",
            "| cores | encoding | driver (read + insert) | job (the larger) |",
            "|---|---|---|---|",
            *projection(r["split"], eff, args.cores),
        ]
    return "\n".join(lines)


def write_docs(text: str) -> None:
    write_section("ingest", "## Ingestion\n\n" + text, DOC)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--photos", type=int, default=24, help="1600 px photos per run (0: skip)")
    ap.add_argument("--crops", type=int, default=64, help="224 px crops per run (0: skip)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--split-images", type=int, default=20, help="images timed stage by stage")
    ap.add_argument("--cores", type=int, nargs="+", default=[8, 16, 32, 64], help="N for the projection")
    ap.add_argument("--write-docs", action="store_true", help="replace the Ingestion table in docs/benchmarks.md")
    args = ap.parse_args()
    if sorted(args.workers)[:2] != [1, 2]:
        raise SystemExit("--workers must include 1 and 2 (the scaling figure compares them)")

    import ray

    from app.ingestion.encoding.ray import connect

    cv2.setNumThreads(1)
    load0 = os.getloadavg()[0]
    connect("local", num_cpus=max(args.workers))
    root = Path(tempfile.mkdtemp(prefix="geoloc-ingest-bench-"))
    try:
        results = [
            measure(kind, n, args, root) for kind, n in (("photos", args.photos), ("crops", args.crops)) if n > 0
        ]
    finally:
        ray.shutdown()
        shutil.rmtree(root, ignore_errors=True)
    text = report(results, args, (load0, os.getloadavg()[0]))
    print(text)
    if args.write_docs:
        write_docs(text)
        print(f"written to {DOC}")


if __name__ == "__main__":
    main()
