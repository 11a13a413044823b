"""/locate p50 of two configurations on real servers, interleaved query by query (issue 11's speed goal).

    .venv/bin/python -m bench.compare_configs [--configs hybrid,hybrid-xfeat] [--reps 3]

Both servers hold the same collection (the penn db photos minus the query captures, encoded in this
process through the core: ``GeolocService.accept`` then the local engine) and get the same 1600 px query
photos, alternating which one goes first, so both see the same machine load. The wall time is measured
by the client around each POST /locate (upload, decode, extract, encode, search, answer), never summed
from self-reported stages. Also run by `make bench` (bench/benchmarks.py), into its own section.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from app.domain import Upload
from app.encoding import EncodeItem, LocalEngine, encode_and_complete
from app.engine.geo import haversine_m
from app.usecases.service import GeolocService
from bench.common import REPO, is_photo, machine, median_ms, penn_rows, percentiles, write_section
from tools.server_process import ServerProcess

COMMAND = ".venv/bin/python -m bench.compare_configs"


def seed(data_dir: Path, models_dir: Path, config: str, rows) -> int:
    service = GeolocService.open(data_dir, models_dir, config)
    uploads = [Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in rows]
    accepted = service.accept(uploads, source="bench")
    paths = {i: service.store.image_path(i) for i in accepted.reference_ids}
    items = [EncodeItem(i, p) for i, p in paths.items()]
    done = encode_and_complete(service, items, LocalEngine(service.pipeline, service.limits, threads=2))
    service.collection.write_snapshot()
    return done


def run(models_dir: Path, configs: list[str], reps: int, manifest: Path | None = None, limit: int = 0) -> dict:
    rows = penn_rows(manifest) if manifest is not None else penn_rows()
    queries = [r for r in rows if r.split == "query" and is_photo(r)][: limit or None]
    groups = {r.group for r in queries}
    collection = [r for r in rows if r.split == "db" and is_photo(r) and r.group not in groups]
    payloads = [(r, r.image.read_bytes()) for r in queries]
    out = {"configs": configs, "collection": len(collection), "queries": len(queries), "reps": reps}
    with tempfile.TemporaryDirectory(prefix="geoloc-compare-") as tmp:
        servers: list[ServerProcess] = []  # by position: the same configuration may be compared with itself
        try:
            for n, c in enumerate(configs):
                print(f"seeding {c}: {len(collection)} references ...", flush=True)
                data = Path(tmp) / f"{n}-{c}"
                seed(data, models_dir, c, collection)
                servers.append(ServerProcess(data, models_dir, c, api_key="bench"))
            for s in servers:
                s.wait_ready(timeout=600)
            wall: list[list[float]] = [[] for _ in configs]
            hits: list[list[bool]] = [[] for _ in configs]
            for _, data in payloads:  # warm: onnxruntime pays once per input shape
                for s in servers:
                    s.client.post("/locate", files=[("image", ("q.jpg", data, "image/jpeg"))]).raise_for_status()
            turn = 0
            for _ in range(reps):
                for row, data in payloads:
                    order = list(range(len(configs)))
                    if turn % 2:
                        order.reverse()
                    turn += 1
                    for k in order:
                        t0 = time.perf_counter()
                        r = servers[k].client.post("/locate", files=[("image", ("q.jpg", data, "image/jpeg"))])
                        wall[k].append((time.perf_counter() - t0) * 1000)
                        r.raise_for_status()
                        top = r.json()["candidates"][:1]
                        hits[k].append(bool(top) and haversine_m(row.lat, row.lon, top[0]["lat"], top[0]["lon"]) <= 25)
        finally:
            for s in servers:
                s.stop()
    out["results"] = [
        {
            "config": c,
            **{f"{k}_ms": v for k, v in percentiles(wall[n]).items()},
            "ratio_p50": median_ms(wall[n]) / median_ms(wall[0]),
            "top1_within_25m": sum(hits[n]) / len(hits[n]),
            "requests": len(wall[n]),
        }
        for n, c in enumerate(configs)
    ]
    return out


def render(fig: dict, command: str) -> str:
    base = fig["configs"][0]
    L = [
        "## /locate by configuration, interleaved on two real servers",
        "",
        f"`{command}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {machine()}): both servers hold the "
        f"same {fig['collection']} penn db photos; {fig['queries']} query photos at 1600 px x {fig['reps']}, "
        "alternating which server goes first; client wall time per POST /locate.",
        "",
        f"| configuration | p50 ms | p95 ms | p50 vs {base} | top-1 within 25 m |",
        "|---|---|---|---|---|",
    ]
    for r in fig["results"]:
        L.append(
            f"| {r['config']} | {r['p50_ms']:.0f} | {r['p95_ms']:.0f} | {r['ratio_p50']:.2f} | "
            f"{r['top1_within_25m']:.0%} |"
        )
    return "\n".join(L)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", default="hybrid,hybrid-xfeat")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--manifest", type=Path, default=None, help="default: data/manifests/penn-campus-gps.csv")
    ap.add_argument("--limit", type=int, default=0, help="first N query photos (0: all)")
    ap.add_argument("--no-doc", action="store_true", help="print only; leave docs/BENCHMARKS.md alone")
    args = ap.parse_args()
    os.environ.setdefault("GEOLOC_FAISS_THREADS", "1")
    fig = run(args.models_dir, args.configs.split(","), args.reps, args.manifest, args.limit)
    text = render(fig, " ".join([COMMAND, *sys.argv[1:]]))
    print(text)
    if not args.no_doc:
        write_section("configs", text)


if __name__ == "__main__":
    main()
