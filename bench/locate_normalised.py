"""/locate p50 through a real server, divided by the p50 of a fixed CPU workload timed interleaved with it.

Why a ratio: the machine is shared (other builds and evaluations come and go), so a /locate time alone says
as much about the neighbours as about the service. A fixed workload timed in the same run, turn by turn
with the requests, slows down with them; the ratio stays put. The workload (issue 21): 2x OpenCV SIFT
(1,000 features) on one 640 x 480 grey image, plus 20 products of two 384 x 384 float32 matrices.

Starts ``geoloc serve`` (tools/server_process.py) on a temporary data dir with the models dir's fitted
``--config`` (when the models dir has none, one fitted on 40 penn images into out/bench-models/, kept for
the next run: the fitted state changes no timing), indexes penn db references through POST /references,
then per round: the workload, a /locate of a 1600 px penn photo, the workload, a /locate of a 12 MP
original (photos-full, 4000 x 3000). Prints p50s and the ratios; ``--write`` puts them in docs/benchmarks.md.

    .venv/bin/python -m bench.locate_normalised --rounds 30
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from app.engine.configs import DEFAULT_CONFIG, get_config
from app.engine.pipeline import Pipeline, pipeline_dir
from app.settings import Settings
from bench.common import REPO, is_photo, machine, penn_rows, percentiles, post_references, write_section
from tools.server_process import ServerProcess

SIFT_FEATURES = 1000
MATMUL_SIDE = 384
MATMULS = 20


class Workload:
    """The fixed CPU workload: 2x SIFT on one 640 x 480 grey penn photo, 20 float32 384 x 384 products."""

    def __init__(self, photo: Path):
        grey = cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE)
        self.grey = cv2.resize(grey, (640, 480), interpolation=cv2.INTER_AREA)
        self.sift = cv2.SIFT_create(nfeatures=SIFT_FEATURES)
        rng = np.random.default_rng(0)
        self.a = rng.standard_normal((MATMUL_SIDE, MATMUL_SIDE)).astype(np.float32)
        self.b = rng.standard_normal((MATMUL_SIDE, MATMUL_SIDE)).astype(np.float32)

    def run(self) -> float:
        """Seconds for one pass."""
        t0 = time.perf_counter()
        for _ in range(2):
            self.sift.detectAndCompute(self.grey, None)
        for _ in range(MATMULS):
            self.a @ self.b
        return time.perf_counter() - t0


def fitted_models(models_dir: Path, config: str, rows, work: Path = REPO / "out" / "bench-models") -> Path:
    """``models_dir`` when ``config`` is fitted there; else ``work`` with links to the built models and
    ``config`` fitted on 40 penn db/train images (each decoded as the pipeline decodes)."""
    if pipeline_dir(models_dir, config).exists():
        return models_dir
    if pipeline_dir(work, config).exists():
        return work
    work.mkdir(parents=True, exist_ok=True)
    for built in models_dir.glob("*.onnx"):
        if not (work / built.name).exists():
            (work / built.name).symlink_to(built.resolve())
    pipe = Pipeline(get_config(config), models_dir=work)
    train = [r for r in rows if r.split in ("db", "train")][:40]
    pipe.fit([pipe.extract(pipe.decode(r.image.read_bytes()).rgb) for r in train])
    pipe.save(pipeline_dir(work, config))
    print(f"fitted {config} on {len(train)} penn images into {work}")
    return work


def locate_seconds(server: ServerProcess, name: str, data: bytes) -> float:
    t0 = time.perf_counter()
    r = server.client.post("/locate", files=[("image", (name, data, "image/jpeg"))], timeout=600)
    seconds = time.perf_counter() - t0
    r.raise_for_status()
    return seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--config", default=DEFAULT_CONFIG, help="a configuration fitted in the models dir")
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--references", type=int, default=64, help="db rows indexed before timing")
    ap.add_argument("--write", action="store_true", help="write the figures into docs/benchmarks.md")
    ap.add_argument(
        "--baseline-tree",
        type=Path,
        help="another checkout (e.g. `git worktree add ../base <commit>`, beside this one so ../shared "
        "resolves): its server runs beside this one's, each request and workload pass interleaved",
    )
    ap.add_argument(
        "--baseline-config",
        help="the configuration the baseline tree serves (default: --config), fitted in the same models dir",
    )
    args = ap.parse_args()
    baseline_config = args.baseline_config or args.config

    rows = penn_rows()
    if args.baseline_tree is not None and baseline_config != args.config:
        missing = [c for c in (args.config, baseline_config) if not pipeline_dir(args.models_dir, c).exists()]
        if missing:  # both servers read one models dir: fitted there, not on 40 images in out/bench-models
            raise SystemExit(f"fit {' and '.join(missing)} in {args.models_dir} first (geoloc fit --config ...)")
    models = fitted_models(args.models_dir, args.config, rows)
    queries = [r for r in rows if is_photo(r) and r.split == "query"]
    groups = {r.group for r in queries}
    refs = [r for r in rows if r.split == "db" and r.group not in groups][: args.references]
    full_dir = Settings().shared_dir / "data" / "penn-campus-gps" / "photos-full"
    originals = sorted(full_dir.glob("*.jpg"))
    if not queries or not originals:
        raise SystemExit(f"need penn query photos and 12 MP originals in {full_dir}")
    q1600 = [(r.image.name, r.image.read_bytes()) for r in queries]
    q12mp = [(p.name, p.read_bytes()) for p in originals]
    workload = Workload(queries[0].image)

    trees = {"": None} if args.baseline_tree is None else {"": None, "baseline ": args.baseline_tree.resolve()}
    times: dict[str, list[float]] = {"workload": []}
    for tree in trees:
        times |= {f"{tree}1600 px": [], f"{tree}12 MP": []}
    with tempfile.TemporaryDirectory(prefix="locate-normalised-") as tmp:
        servers = {
            tree: ServerProcess(Path(tmp) / f"data{n}", models, baseline_config if code else args.config, code=code)
            for n, (tree, code) in enumerate(trees.items())
        }
        try:
            for server in servers.values():
                server.wait_ready(timeout=300)
                post_references(server.client, [(r.image.name, r.image.read_bytes(), r.lat, r.lon) for r in refs])
                for name, data in (q1600[0], q12mp[0]):  # models loaded, caches warm
                    locate_seconds(server, name, data)
            workload.run()
            for i in range(args.rounds):
                order = list(servers.items()) if i % 2 == 0 else list(servers.items())[::-1]
                for tree, server in order:
                    times["workload"].append(workload.run())
                    times[f"{tree}1600 px"].append(locate_seconds(server, *q1600[i % len(q1600)]))
                    times["workload"].append(workload.run())
                    times[f"{tree}12 MP"].append(locate_seconds(server, *q12mp[i % len(q12mp)]))
                if (i + 1) % 10 == 0:
                    print(f"  round {i + 1}/{args.rounds}", flush=True)
        finally:
            for server in servers.values():
                server.stop()

    p = {k: percentiles(v, (50, 95)) for k, v in times.items()}
    w50 = p["workload"]["p50"]
    ratio = p["1600 px"]["p50"] / w50
    large = p["12 MP"]["p50"] / p["1600 px"]["p50"]
    lines = [
        "## /locate normalised by a fixed CPU workload",
        "",
        f"`python -m bench.locate_normalised --config {args.config} --rounds {args.rounds}` ({machine()}): "
        f"a real server (`geoloc serve`, {args.config}, {len(refs)} penn references), /locate of the "
        f"{len(q1600)} 1600 px penn query photos and of the {len(q12mp)} 12 MP originals in turn, each after one "
        f"pass of the workload (2x OpenCV SIFT with {SIFT_FEATURES} features on one 640 x 480 grey image, plus "
        f"{MATMULS} products of two {MATMUL_SIDE} x {MATMUL_SIDE} float32 matrices) timed in the bench process. "
        "The ratio, not the milliseconds, is the figure to compare across runs and machines.",
        "",
        "| timed | p50 ms | p95 ms | p50 / workload p50 |",
        "|---|---|---|---|",
    ]
    for k in times:
        lines.append(
            f"| {k if k == 'workload' else '/locate ' + k} | {p[k]['p50'] * 1000:.1f} | {p[k]['p95'] * 1000:.1f} "
            f"| {p[k]['p50'] / w50:.2f} |"
        )
    lines += ["", f"- /locate 1600 px p50 / workload p50: **{ratio:.2f}**; 12 MP p50 / 1600 px p50: **{large:.2f}**."]
    if args.baseline_tree is not None:
        lines.append(
            f"- Against the baseline tree ({args.baseline_tree.name}, serving {baseline_config}), interleaved request "
            "by request: 1600 px "
            f"p50 **{p['1600 px']['p50'] / p['baseline 1600 px']['p50']:.2f}x**, 12 MP p50 "
            f"**{p['12 MP']['p50'] / p['baseline 12 MP']['p50']:.2f}x** the baseline's."
        )
    text = "\n".join(lines)
    print("\n" + text)
    if args.write:
        write_section("locate-normalised", text)


if __name__ == "__main__":
    main()
