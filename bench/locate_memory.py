"""Memory of a real server under 8 concurrent 49 MP /locate uploads.

Starts ``geoloc serve`` (app/server_process.py) on a temporary data dir with a fitted pipeline and a few
penn references, then per burst: samples the server's RSS at idle, sends N concurrent /locate with the same
49 MP image (a flat PNG declaring 7000 x 7000, tens of KB, or a 7000 x 7000 JPEG upscaled from a penn
photo), samples RSS every 50 ms for the peak, and for --after seconds once all answers are in. Each
setting runs in a fresh server; the old settings (no /locate limit, no malloc trim) are the baseline,
measured in the same process. Prints medians over --repeats; --write puts them in docs/benchmarks.md.

    .venv/bin/python -m bench.locate_memory --repeats 2
"""

from __future__ import annotations

import argparse
import io
import statistics
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
from PIL import Image

from app.engine.configs import get_config
from app.engine.pipeline import pipeline_dir
from app.settings import Settings, usable_cpus
from bench.common import REPO, is_photo, machine, penn_rows, post_references, write_section
from tools.process_memory import MiB, PeakRss, rss_bytes
from tools.server_process import ServerProcess

SIDE = 7000  # 49 MP, under the 50 MP default limit
SETTINGS = {  # label -> server environment
    "old settings (no limit, no trim)": {"GEOLOC_LOCATE_CONCURRENCY": "0", "GEOLOC_MALLOC_TRIM": "0"},
    "defaults": {},
}
WARM: Path  # a 1600 px penn photo that warms a server up
NOTE = (
    "The defaults: at most one /locate per usable CPU decoding and extracting at once "
    "(`GEOLOC_LOCATE_CONCURRENCY`), `malloc_trim(0)` after each upload larger than twice the decode size "
    "(`GEOLOC_MALLOC_TRIM=0` turns it off). Both rows run the same decoding code: a PNG/WebP/TIFF above "
    "3200 px is reduced right after its full-size decode (JPEG is scaled while decoding), at most 50 MP of "
    "full-size decodes at once in the process. Before that change one 49 MP PNG decode alone peaked at +655 MB "
    "(the decode, orientation and RGB copies, and the 147 MB array it returned); now at most +200 MB, and "
    "it returns a 9 MB array (one `load_image` in a fresh process, peak VmHWM)."
)


def flat_png() -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (SIDE, SIDE), (118, 130, 141)).save(buf, "PNG", optimize=True)
    return buf.getvalue()


def big_jpeg(photo: Path) -> bytes:
    img = cv2.imread(str(photo))
    img = cv2.resize(img, (SIDE, SIDE), interpolation=cv2.INTER_LINEAR)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return buf.tobytes()


def ensure_models(models_dir: Path, config: str, rows, work: Path = REPO / "out" / "bench-models") -> Path:
    """``models_dir`` when it holds a fitted ``config``; else ``work`` (kept for the next run) with the
    SqueezeNet ONNX built from the shared IR and ``config`` fitted on 40 penn images, as the tests do."""
    if pipeline_dir(work, config).exists():
        return work
    if pipeline_dir(models_dir, config).exists() and (models_dir / "squeezenet1_1.onnx").exists():
        return models_dir
    from app.engine.convert.squeezenet_onnx import build_squeezenet_onnx
    from app.engine.imageio import load_image
    from app.engine.models.squeezenet import MODEL_FILENAME, SqueezeNet
    from app.engine.pipeline import Pipeline

    out = work
    out.mkdir(parents=True, exist_ok=True)
    for extra in models_dir.glob("xfeat*"):  # the vendored XFeat model, for configurations that use it
        (out / extra.name).write_bytes(extra.read_bytes())
    build_squeezenet_onnx(
        Settings().shared_dir / "models" / "squeezenet1.1" / "caffe-openvino-ir", out / MODEL_FILENAME
    )
    cnn = SqueezeNet(out / MODEL_FILENAME)
    cnn.load()
    pipe = Pipeline(get_config(config), global_model=cnn)
    train = [r for r in rows if r.split in ("db", "train")][:40]
    pipe.fit([pipe.extract(load_image(r.image.read_bytes()).rgb) for r in train])
    pipe.save(pipeline_dir(out, config))
    print(f"fitted {config} on {len(train)} penn images into {out}")
    return out


@dataclass
class Burst:
    idle: int
    peak: int
    after: int  # RSS --after seconds after the last answer
    back_s: float | None  # seconds after the last answer until RSS was within 20 % of idle (None: never)
    seconds: float
    statuses: list[int]


def burst(server: ServerProcess, data: bytes, name: str, n: int, after_s: float) -> Burst:
    pid = server.proc.pid
    time.sleep(2.0)
    idle = rss_bytes(pid)

    def one(_: int) -> int:
        with httpx.Client(base_url=server.url, timeout=600) as c:
            return c.post("/locate", files=[("image", (name, data, "application/octet-stream"))]).status_code

    t0 = time.perf_counter()
    with PeakRss(pid, every_s=0.05) as sampler, ThreadPoolExecutor(n) as pool:
        statuses = list(pool.map(one, range(n)))
    seconds = time.perf_counter() - t0
    peak = sampler.peak
    end = time.monotonic() + after_s
    back_s = None
    t_last = time.monotonic()
    while time.monotonic() < end:
        rss = rss_bytes(pid)
        peak = max(peak, rss)
        if back_s is None and rss <= idle * 1.2:
            back_s = time.monotonic() - t_last
        time.sleep(0.5)
    return Burst(idle, peak, rss_bytes(pid), back_s, seconds, statuses)


def run_setting(env: dict, data_dir: Path, models: Path, config: str, kind: str, data: bytes, n, after_s, seed):
    """One burst on a fresh server: what one burst leaves behind must not be the next one's idle."""
    server = ServerProcess(data_dir, models, config, extra_env={"GEOLOC_ORT_THREADS": "1", **env})
    with server:
        post_references(server.client, seed, batch=8)
        warm = WARM.read_bytes()
        for _ in range(2):  # models loaded and warmed on a normal photo: that is the idle state
            server.client.post("/locate", files=[("image", ("w.jpg", warm, "image/jpeg"))]).raise_for_status()
        return burst(server, data, f"q.{kind.lower()}", n, after_s)


def med(values) -> float:
    return float(statistics.median(values))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--config", default="hybrid-nobank", help="the default hybrid's extraction, no SVM bank to fit")
    ap.add_argument("--concurrent", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--after", type=float, default=60.0, help="seconds of RSS samples after a burst")
    ap.add_argument("--write", action="store_true", help="write the figures into docs/benchmarks.md")
    args = ap.parse_args()

    global WARM
    rows = penn_rows()
    photos = [r for r in rows if is_photo(r)]
    WARM = photos[1].image
    payloads = {"PNG": flat_png(), "JPEG": big_jpeg(photos[0].image)}
    crops = [r for r in rows if r.image.parent.name == "crops" and r.split == "db"]
    seed = [(r.image.name, r.image.read_bytes(), r.lat, r.lon) for r in crops[:16]]  # 224 px: quick to index
    print(f"payloads: PNG {len(payloads['PNG']) / 1024:.0f} KB, JPEG {len(payloads['JPEG']) / MiB:.1f} MB, "
          f"{SIDE} x {SIDE}; {args.concurrent} concurrent; {usable_cpus()} usable CPUs")  # fmt: skip
    results: dict[str, dict[str, list[Burst]]] = {label: {k: [] for k in payloads} for label in SETTINGS}
    with tempfile.TemporaryDirectory(prefix="locate-memory-") as tmp:
        work = Path(tmp)
        models = ensure_models(args.models_dir, args.config, rows)
        for rep in range(args.repeats):
            for kind, data in payloads.items():
                for i, (label, env) in enumerate(SETTINGS.items()):  # interleaved: both see the same machine
                    data_dir = work / f"data-{rep}-{kind}-{i}"
                    b = run_setting(env, data_dir, models, args.config, kind, data, args.concurrent, args.after, seed)
                    results[label][kind].append(b)
                    print(
                        f"  rep {rep} {label:34s} {kind:4s}: idle {b.idle / MiB:.0f} MB, "
                        f"peak +{(b.peak - b.idle) / MiB:.0f} MB, "
                        f"after {args.after:.0f} s +{(b.after - b.idle) / MiB:.0f} MB, back within 20 % after "
                        f"{b.back_s if b.back_s is None else round(b.back_s, 1)} s, {b.seconds:.1f} s, {b.statuses}",
                        flush=True,
                    )

    lines = [
        "## /locate memory: 8 concurrent 49 MP uploads",
        "",
        f"`python -m bench.locate_memory --repeats {args.repeats}` ({args.config}, {machine()}; "
        f"{usable_cpus()} usable CPUs): the server's RSS (VmRSS) at idle, its peak rise during "
        f"{args.concurrent} concurrent /locate of one {SIDE} x {SIDE} image, and its rise {args.after:.0f} s after "
        f"the last answer; medians over {args.repeats} fresh servers per setting. PNG: flat, "
        f"{len(payloads['PNG']) / 1024:.0f} KB; JPEG: a penn photo upscaled, {len(payloads['JPEG']) / MiB:.1f} MB.",
        "",
        "| setting | image | idle MB | peak rise MB | rise after MB | back within 20 % of idle after s | burst s |",
        "|---|---|---|---|---|---|---|",
    ]
    summary = {}
    for label in SETTINGS:
        for kind, bursts in results[label].items():
            rise = med(b.peak - b.idle for b in bursts) / MiB
            kept = med(b.after - b.idle for b in bursts) / MiB
            backs = [b.back_s for b in bursts if b.back_s is not None]
            back = f"{med(backs):.1f}" if len(backs) == len(bursts) else "never (within the window)"
            summary[label, kind] = (rise, kept)
            lines.append(
                f"| {label} | {kind} | {med(b.idle for b in bursts) / MiB:.0f} | {rise:.0f} | {kept:.0f} | {back} "
                f"| {med(b.seconds for b in bursts):.1f} |"
            )
    base, new = list(SETTINGS)
    lines += ["", NOTE]
    for kind in payloads:
        (r0, k0), (r1, k1) = summary[base, kind], summary[new, kind]
        lines.append(
            f"- {kind}: peak rise {r1:.0f} MB with the defaults vs {r0:.0f} MB with the old settings "
            f"({r1 / r0:.2f}x); kept after {args.after:.0f} s {k1:.0f} vs {k0:.0f} MB."
        )
    text = "\n".join(lines)
    print("\n" + text)
    if args.write:
        write_section("locate-memory", text)


if __name__ == "__main__":
    main()
