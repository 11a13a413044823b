"""Photos of places a collection holds, located against it: how many get an estimate, and whether the truth
lies within each estimate's stated radius.

    .venv/bin/python -m bench.held_places [--data-dir index] [--models-dir models] [--config lite2-hybrid-384] \
        [--manifest data/manifests/penn-campus-gps.csv] [--held-within 25]
    .venv/bin/python -m bench.held_places --write-subset /tmp/c60.csv [--references 60] [--seed 0]

Why: the counterpart of ``bench.absent_places`` (its goals: the 16 penn query photos against the demo
collection give >= 4 estimates, each within its stated radius; a 60-reference collection gives an estimate
for at least one penn query photo whose place it holds). The photos are the whole photos of the manifest's query
split (the 16 of penn-campus-gps, what the README's stage medians are taken over), their truth the
manifest's position; a photo counts as held when a reference of the collection lies within ``--held-within``
metres of it (every photo is listed, the held ones marked). Each goes through ``GeolocService.locate``, the
use case /locate serves, with the configuration's default verification. Prints one line per photo and the
summary.

``--write-subset``: a small collection's manifest instead (then ``geoloc ingest`` and ``geoloc refit`` it): whole
captures of the manifest's db rows (a photo and its crops), alternately the nearest capture to the next query
photo whose place is not yet held and a seeded random one, until ``--references`` rows; the query rows are
copied, so the same manifest names the photos to locate.
"""

from __future__ import annotations

import argparse
import csv
import functools
from pathlib import Path

import numpy as np

from app.domain import LocateOptions
from app.engine.configs import DEFAULT_CONFIG
from app.engine.geo import haversine_m
from app.manifests import read_manifest
from app.usecases.service import GeolocService

REPO = Path(__file__).resolve().parents[1]


def write_subset(manifest: Path, out: Path, references: int, seed: int, held_within: float) -> None:
    rows = read_manifest(manifest)
    captures: dict[str, list] = {}
    for r in rows:
        if r.split == "db":
            captures.setdefault(r.group, []).append(r)
    queries = [r for r in rows if r.split == "query" and r.image.stem == r.group]
    rest = sorted(captures)
    np.random.default_rng(seed).shuffle(rest)
    chosen: list[str] = []

    def holds(q) -> bool:
        return any(
            float(haversine_m(q.lat, q.lon, captures[g][0].lat, captures[g][0].lon)) <= held_within for g in chosen
        )

    sizes = {len(c) for c in captures.values()}

    @functools.cache
    def fillable(n: int) -> bool:  # n rows can be made of whole captures (sizes assumed plentiful)
        return n == 0 or (n > 0 and any(fillable(n - k) for k in sizes))

    near_turn = True
    while (left := references - sum(len(captures[g]) for g in chosen)) > 0:
        unheld = [q for q in queries if not holds(q)]
        free = [g for g in rest if g not in chosen]
        fits = [g for g in free if fillable(left - len(captures[g]))] or free  # exactly the size, if it can be
        if near_turn and unheld:
            q = unheld[0]
            g = min(fits, key=lambda g: float(haversine_m(q.lat, q.lon, captures[g][0].lat, captures[g][0].lon)))
        else:
            g = fits[0]
        chosen.append(g)
        near_turn = not near_turn
    with out.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "lat", "lon", "split", "group"])
        for r in [r for g in chosen for r in captures[g]] + [r for r in rows if r.split == "query"]:
            w.writerow([r.image, f"{r.lat:.8f}", f"{r.lon:.8f}", r.split, r.group])
    n = sum(len(captures[g]) for g in chosen)
    held = sum(map(holds, queries))
    print(f"wrote {out}: {n} db rows in {len(chosen)} captures ({', '.join(chosen)}); holds {held} of {len(queries)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", type=Path, default=REPO / "index")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--manifest", type=Path, default=REPO / "data/manifests/penn-campus-gps.csv")
    ap.add_argument("--held-within", type=float, default=25.0, help="metres: a reference this near holds the place")
    ap.add_argument("--write-subset", type=Path, help="write a small collection's manifest here and stop")
    ap.add_argument("--references", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.write_subset:
        write_subset(args.manifest, args.write_subset, args.references, args.seed, args.held_within)
        return
    service = GeolocService.open(args.data_dir, args.models_dir, args.config)
    refs: list = []
    while len(page := service.list(len(refs), 1000)[0]):
        refs += page
    total = len(refs)
    ref_lat = np.array([r.lat for r in refs])
    ref_lon = np.array([r.lon for r in refs])
    rows = [r for r in read_manifest(args.manifest) if r.split == "query" and r.image.stem == r.group]
    held = estimates = within = top1 = 0
    for row in rows:
        near = float(np.min(haversine_m(row.lat, row.lon, ref_lat, ref_lon))) if len(refs) else float("inf")
        is_held = near <= args.held_within
        a = service.locate(row.image.read_bytes(), LocateOptions(top_k=10))
        c0 = a.candidates[0] if a.candidates else None
        top1_ok = c0 is not None and float(haversine_m(row.lat, row.lon, c0.lat, c0.lon)) <= 25.0
        best_p = max((c.p_within_25m for c in a.candidates if c.p_within_25m is not None), default=None)
        line = f"{row.image.name}: {'held' if is_held else 'not held'} (nearest ref {near:.0f} m), top-1 "
        line += f"{'within' if top1_ok else 'beyond'} 25 m, best p {'n/a' if best_p is None else f'{best_p:.3f}'}, "
        held += is_held
        top1 += top1_ok and is_held
        e = a.estimate
        if a.reason is None and e.lat is not None:
            err = float(haversine_m(row.lat, row.lon, e.lat, e.lon))
            ok = e.radius_m is not None and err <= e.radius_m
            estimates += 1
            within += ok
            rate = "constant rule" if e.radius_rate is None else f"rate {e.radius_rate:.2f}"
            line += (
                f"ESTIMATE {err:.0f} m off, stated radius {e.radius_m:.0f} m ({rate}): {'holds' if ok else 'MISSED'}"
            )
        else:
            line += f"no estimate ({a.reason_code})"
        print(line)
    print(
        f"{len(rows)} query photos against {args.data_dir} ({total} references, {args.config}): {held} held; "
        f"top-1 within 25 m for {top1} of the held; {estimates} estimates, {within} within their stated radius"
    )


if __name__ == "__main__":
    main()
