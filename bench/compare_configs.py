"""/locate p50 of two configurations on real servers, interleaved query by query.

    .venv/bin/python -m bench.compare_configs [--configs hybrid,hybrid-xfeat] [--reps 3]
    .venv/bin/python -m bench.compare_configs --configs lite2-hybrid-384-sv:rerank=false,lite2-hybrid-384-sv
    .venv/bin/python -m bench.compare_configs --configs lite2-hybrid-384,lite2-hybrid-384:milvus --references 10000

A side is a configuration, optionally with ``:rerank=true`` or ``:rerank=false`` (the form field each of its
requests sends; none: the configuration's default), so one configuration with and without verification
runs on two servers holding copies of one seeded data dir; or with ``:milvus``, its server's index on a
Milvus standalone this bench starts from the ``milvus`` wheel (``GEOLOC_MILVUS_URI``), against the same
collection on the data dir's own FAISS index. ``--references N`` fills each data dir up to N references with
synthetic codes after the penn photos (``bench.seed``), so the search runs at that size.

Both servers hold the same collection (the penn db photos minus the query captures, encoded in this
process through the core: ``GeolocService.accept`` then the local engine) and get the same 1600 px query
photos, alternating which one goes first, so both see the same machine load. The wall time is measured
by the client around each POST /locate (upload, decode, extract, encode, search, answer), never summed
from self-reported stages. Also run by `make bench` (bench/benchmarks.py), into its own section.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from app.domain import Upload
from app.engine.geo import haversine_m
from app.ingestion.encoding.items import EncodeItem
from app.ingestion.encoding.local import LocalEngine, encode_and_complete
from app.usecases.service import GeolocService
from bench.common import REPO, is_photo, machine, median_ms, penn_rows, percentiles, write_section
from bench.seed import seed as seed_synthetic
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


def side(spec: str) -> tuple[str, dict[str, str], bool]:
    """``config[:rerank=true|false][:milvus]`` -> (config, the form fields each /locate request of that side
    sends, whether its index is on Milvus)."""
    config, *options = spec.split(":")
    form: dict[str, str] = {}
    milvus = False
    for option in options:
        key, _, value = option.partition("=")
        if key == "rerank" and value in ("true", "false"):
            form["rerank"] = value
        elif option == "milvus":
            milvus = True
        else:
            raise SystemExit(f"{spec}: a side is CONFIG[:rerank=true|false][:milvus]")
    return config, form, milvus


def run(
    models_dir: Path, configs: list[str], reps: int, manifest: Path | None = None, limit: int = 0, references: int = 0
) -> dict:
    rows = penn_rows(manifest) if manifest is not None else penn_rows()
    queries = [r for r in rows if r.split == "query" and is_photo(r)][: limit or None]
    groups = {r.group for r in queries}
    collection = [r for r in rows if r.split == "db" and is_photo(r) and r.group not in groups]
    payloads = [(r, r.image.read_bytes()) for r in queries]
    out = {"configs": configs, "collection": len(collection), "queries": len(queries), "reps": reps}
    sides = [side(spec) for spec in configs]
    with tempfile.TemporaryDirectory(prefix="geoloc-compare-") as tmp:
        servers: list[ServerProcess] = []  # by position: the same configuration may be compared with itself
        seeded: dict[str, Path] = {}  # a configuration's seeded data dir: a second side of it gets a copy
        milvus = None
        try:
            for n, (c, _, _) in enumerate(sides):
                data = Path(tmp) / f"{n}-{c}"
                if c in seeded:
                    shutil.copytree(seeded[c], data)
                else:
                    print(f"seeding {c}: {len(collection)} references ...", flush=True)
                    seed(data, models_dir, c, collection)
                    if references > len(collection):
                        print(f"  and synthetic ones up to {references} ...", flush=True)
                        seed_synthetic(data, references, models_dir, c)
                        GeolocService.open(data, models_dir, c).collection.write_snapshot()
                    seeded[c] = data
            if any(on_milvus for _, _, on_milvus in sides):
                from tools.milvus_server import MilvusServer

                milvus = MilvusServer(Path(tmp) / "milvus").start()
            for n, (c, _, on_milvus) in enumerate(sides):
                env = {"GEOLOC_MILVUS_URI": milvus.uri, "GEOLOC_MILVUS_COLLECTION": f"bench{n}"} if on_milvus else {}
                servers.append(ServerProcess(Path(tmp) / f"{n}-{c}", models_dir, c, api_key="bench", extra_env=env))
            for s in servers:
                s.wait_ready(timeout=1200)
            ready = [s.client.get("/ready").json() for s in servers]
            out["references"] = [r.get("index_size") for r in ready]
            out["kinds"] = [{part: i.get("kind") for part, i in (r.get("index") or {}).items()} for r in ready]
            out["load_before"] = os.getloadavg()
            wall: list[list[float]] = [[] for _ in configs]
            hits: list[list[bool]] = [[] for _ in configs]
            verified: list[list[int]] = [[] for _ in configs]  # candidates carrying inliers, per answer
            for _, data in payloads:  # warm: onnxruntime pays once per input shape
                for s, (_, form, _) in zip(servers, sides, strict=True):
                    image = [("image", ("q.jpg", data, "image/jpeg"))]
                    s.client.post("/locate", files=image, data=form).raise_for_status()
            turn = 0
            for _ in range(reps):
                for row, data in payloads:
                    order = list(range(len(configs)))
                    if turn % 2:
                        order.reverse()
                    turn += 1
                    for k in order:
                        image = [("image", ("q.jpg", data, "image/jpeg"))]
                        t0 = time.perf_counter()
                        r = servers[k].client.post("/locate", files=image, data=sides[k][1])
                        wall[k].append((time.perf_counter() - t0) * 1000)
                        r.raise_for_status()
                        top = r.json()["candidates"][:1]
                        hits[k].append(bool(top) and haversine_m(row.lat, row.lon, top[0]["lat"], top[0]["lon"]) <= 25)
                        verified[k].append(sum(c["inliers"] is not None for c in r.json()["candidates"]))
            out["load_after"] = os.getloadavg()
        finally:
            for s in servers:
                s.stop()
            if milvus is not None:
                milvus.stop()
    out["results"] = [
        {
            "config": c,
            **{f"{k}_ms": v for k, v in percentiles(wall[n]).items()},
            "ratio_p50": median_ms(wall[n]) / median_ms(wall[0]),
            "top1_within_25m": sum(hits[n]) / len(hits[n]),
            "requests": len(wall[n]),
            "verified_mean": sum(verified[n]) / len(verified[n]),
        }
        for n, c in enumerate(configs)
    ]
    return out


def _synthetic(fig: dict) -> str:
    n = max(fig["references"] or [0])
    return f" and synthetic references up to {n:,}" if n > fig["collection"] else ""


def render(fig: dict, command: str) -> str:
    base = fig["configs"][0]
    L = [
        "## /locate by configuration, interleaved on two real servers",
        "",
        f"`{command}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {machine()}): both servers hold the "
        f"same {fig['collection']} penn db photos{_synthetic(fig)}; {fig['queries']} query photos at 1600 px x "
        f"{fig['reps']}, "
        "alternating which server goes first; client wall time per POST /locate. Load average (1 min) "
        f"{fig['load_before'][0]:.1f} before the timed requests, {fig['load_after'][0]:.1f} after.",
        "",
        f"| configuration | p50 ms | p95 ms | p50 vs {base} | top-1 within 25 m | candidates verified (mean) |",
        "|---|---|---|---|---|---|",
    ]
    for r, kinds in zip(fig["results"], fig["kinds"], strict=True):
        index = ", ".join(f"{part} {kind}" for part, kind in kinds.items())
        L.append(
            f"| {r['config']} ({index}) | {r['p50_ms']:.0f} | {r['p95_ms']:.0f} | {r['ratio_p50']:.2f} | "
            f"{r['top1_within_25m']:.0%} | {r['verified_mean']:.1f} |"
        )
    return "\n".join(L)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", default="hybrid,hybrid-xfeat")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--manifest", type=Path, default=None, help="default: data/manifests/penn-campus-gps.csv")
    ap.add_argument("--limit", type=int, default=0, help="first N query photos (0: all)")
    ap.add_argument("--references", type=int, default=0, help="fill up to N references with synthetic codes")
    ap.add_argument("--no-doc", action="store_true", help="print only; leave docs/benchmarks.md alone")
    args = ap.parse_args()
    os.environ.setdefault("GEOLOC_FAISS_THREADS", "1")
    fig = run(args.models_dir, args.configs.split(","), args.reps, args.manifest, args.limit, args.references)
    text = render(fig, " ".join([COMMAND, *sys.argv[1:]]))
    print(text)
    if not args.no_doc:
        write_section("configs", text)


if __name__ == "__main__":
    main()
