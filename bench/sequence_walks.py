"""A manifest that holds out whole windows of the penn walks, for `geoloc eval --sequence-window`.

The penn-campus-gps photos are walks by three phones in one afternoon (EXIF DateTimeOriginal and Make +
Model). Each phone's photos, in time order, are cut into windows of ``--window`` consecutive photos; the
windows whose number is ``--part`` modulo ``--parts`` are held out: their photos are query rows (one
``sequence`` per window, with its ``time``), and neither they nor any of their crops are in the collection,
so a photo's own crop, or a neighbour's, never answers for it. Every other capture (its photo and its five
crops, and the crops of the captures without an original) is a db row. Running the ``--parts`` parts in turn
holds out every window once.

``--steps`` measures the walks instead: every pair of a camera's consecutive photos, its time gap and its
distance (GPS to GPS), against the motion model's defaults (``app.engine.sequence``): how many steps lie
beyond the distance it calls compatible (the speed bound times the gap, or the step bound, plus its slack)
and how many photos within its burst time lie more than a place apart.

    python -m bench.sequence_walks --out out/walks/penn-walks-0.csv --part 0
    geoloc eval -m out/walks/penn-walks-0.csv --sequence-window 5
    python -m bench.sequence_walks --steps
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from app.engine.geo import haversine_m
from app.engine.sequence import BURST_S, PLACE_RADIUS_M, SLACK_M, Motion
from app.library.photos import read_meta
from app.manifests import Row, write_manifest
from app.usecases.sequence_inputs import seconds

PENN = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "penn-campus-gps"


def walks(source: Path) -> dict[str, list[tuple[dict, float, str]]]:
    """Per camera: its captures with a photo, in time order, each with its time in seconds (on the walk's one
    clock) and as ISO 8601. Photos without a time or a camera are left out (they belong to no walk)."""
    with (source / "index.csv").open(newline="") as f:
        records = [r for r in csv.DictReader(f) if r["photo"]]
    by_camera: dict[str, list[tuple[dict, object]]] = {}
    for r in records:
        meta = read_meta(source / r["photo"])
        if meta.taken is not None and meta.camera:
            by_camera.setdefault(meta.camera, []).append((r, meta.taken))
    out = {}
    for camera, items in sorted(by_camera.items()):
        secs = seconds([t for _, t in items])
        ordered = sorted(zip(items, secs, strict=True), key=lambda x: x[1])
        out[camera] = [(r, s, t.isoformat()) for (r, t), s in ordered]
    return out


def walk_rows(source: Path, window: int, part: int, parts: int) -> list[Row]:
    held: dict[str, tuple[str, str]] = {}  # photo_id -> (sequence, time)
    for camera, photos in walks(source).items():
        for start in range(0, len(photos), window):
            number = start // window
            if number % parts != part or len(photos[start : start + window]) < 2:
                continue
            for r, _, iso in photos[start : start + window]:
                held[r["photo_id"]] = (f"{camera} #{number}", iso)
    rows = []
    with (source / "index.csv").open(newline="") as f:
        for r in csv.DictReader(f):
            pid, lat, lon = r["photo_id"], float(r["lat"]), float(r["lon"])
            if pid in held:
                sequence, time = held[pid]
                rows.append(Row((source / r["photo"]).resolve(), lat, lon, "query", pid, sequence, time))
                continue
            images = ([r["photo"]] if r["photo"] else []) + [c for c in r["crops"].split(";") if c]
            rows += [Row((source / img).resolve(), lat, lon, "db", pid) for img in images]
    return rows


def steps(source: Path) -> list[tuple[float, float]]:
    """(time gap in seconds, distance in metres) of every pair of a camera's consecutive photos."""
    out = []
    for photos in walks(source).values():
        for (a, sa, _), (b, sb, _) in zip(photos[:-1], photos[1:], strict=True):
            d = haversine_m(float(a["lat"]), float(a["lon"]), float(b["lat"]), float(b["lon"]))
            out.append((sb - sa, float(d)))
    return out


def step_report(measured: list[tuple[float, float]]) -> str:
    """The walks' measured motion against the model's defaults, in lines of text."""
    gap = np.array([g for g, _ in measured])
    dist = np.array([d for _, d in measured])
    moving = gap > 0
    speed = dist[moving] / gap[moving]
    motion = Motion()
    beyond_speed = int((dist > np.array([motion.allowed_m(g) for g in gap]) + SLACK_M).sum())
    beyond_step = int((dist > motion.allowed_m(None) + SLACK_M).sum())
    burst = gap <= BURST_S
    q = (50, 90, 95, 99, 100)
    return "\n".join(
        [
            f"{len(measured)} steps (consecutive photos of one camera)",
            "time gap s, quantiles " + _quantiles(gap, q),
            "distance m, quantiles " + _quantiles(dist, q),
            f"speed m/s ({int(moving.sum())} steps with a gap), quantiles " + _quantiles(speed, q),
            f"beyond the speed bound ({motion.speed_mps} m/s x gap + {SLACK_M:.0f} m): {beyond_speed}",
            f"beyond the step bound ({motion.step_m:.0f} m + {SLACK_M:.0f} m): {beyond_step}",
            f"within {BURST_S:.0f} s: {int(burst.sum())}, of which more than {PLACE_RADIUS_M:.0f} m apart: "
            f"{int((dist[burst] > PLACE_RADIUS_M).sum())}",
        ]
    )


def _quantiles(x: np.ndarray, q: tuple[int, ...]) -> str:
    values = np.percentile(x, q) if len(x) else [float("nan")] * len(q)
    names = ["max" if k == 100 else f"q{k}" for k in q]
    return ", ".join(f"{name} {v:.2f}" for name, v in zip(names, values, strict=True))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", type=Path, default=PENN)
    ap.add_argument("--out", type=Path, help="the manifest to write")
    ap.add_argument("--steps", action="store_true", help="measure the walks' steps instead of writing a manifest")
    ap.add_argument("--window", type=int, default=6, help="consecutive photos per held-out window")
    ap.add_argument("--parts", type=int, default=3, help="hold out one window in this many")
    ap.add_argument("--part", type=int, default=0, help="which windows: their number modulo --parts")
    args = ap.parse_args(argv)
    if args.steps:
        print(step_report(steps(args.source.resolve())))
        return
    if args.out is None:
        ap.error("--out is required (or --steps)")
    if not 0 <= args.part < args.parts or args.window < 2:
        ap.error("need 0 <= --part < --parts and --window >= 2")
    rows = walk_rows(args.source.resolve(), args.window, args.part, args.parts)
    write_manifest(args.out, rows)
    queries = [r for r in rows if r.split == "query"]
    print(
        f"wrote {args.out}: {len(queries)} query photos in {len({r.sequence for r in queries})} windows, "
        f"{len(rows) - len(queries)} db rows"
    )


if __name__ == "__main__":
    main()
