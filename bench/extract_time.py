"""Decode + extraction time of two configurations on the same whole photos, interleaved photo by photo.

Why: ``geoloc eval``'s milliseconds come from runs made at different times on a shared machine; a variant
that adds work to every query (``lite2-hybrid-384-2s``: a second CNN input size) is judged by its time
against the baseline's measured in the same process, on the same photos, alternating which goes first.
CPU time of this process is reported beside wall time (other sessions' load moves wall time, not CPU time).

    .venv/bin/python -m bench.extract_time --configs lite2-hybrid-384,lite2-hybrid-384-2s --photos 30
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path

from app.engine.configs import get_config
from app.engine.pipeline import Pipeline
from bench.common import REPO, is_photo, machine, median_ms, penn_rows


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--configs", default="lite2-hybrid-384,lite2-hybrid-384-2s")
    ap.add_argument("--photos", type=int, default=30)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    a = ap.parse_args(argv)
    names = a.configs.split(",")
    pipes = [Pipeline(get_config(names[0]), models_dir=a.models_dir)]
    pipes += [Pipeline(get_config(n), pipes[0].global_model, models_dir=a.models_dir) for n in names[1:]]
    for p in pipes:
        p.load_models()
    photos = [r.image.read_bytes() for r in penn_rows() if is_photo(r)][: a.photos]
    for p in pipes:  # warm-up: sessions, arenas
        p.extract(p.decode(photos[0]).rgb)
    wall: dict[str, list[float]] = {n: [] for n in names}
    cpu: dict[str, list[float]] = {n: [] for n in names}
    for rep in range(a.reps):
        for i, data in enumerate(photos):
            order = list(zip(names, pipes, strict=True))
            if (i + rep) % 2:
                order.reverse()
            for name, pipe in order:
                w0, c0 = time.perf_counter(), time.process_time()
                pipe.extract(pipe.decode(data).rgb)
                wall[name].append((time.perf_counter() - w0) * 1000)
                cpu[name].append((time.process_time() - c0) * 1000)
    print(f"{machine()}; {len(photos)} whole photos x {a.reps}, interleaved; decode + extract per photo")
    base = names[0]
    for n in names:
        print(
            f"{n}: wall {median_ms(wall[n]):.1f} ms ({median_ms(wall[n]) / median_ms(wall[base]):.2f}x), "
            f"CPU {median_ms(cpu[n]):.1f} ms ({median_ms(cpu[n]) / median_ms(cpu[base]):.2f}x)"
        )


if __name__ == "__main__":
    main()
