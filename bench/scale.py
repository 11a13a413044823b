"""The service at collection sizes users have: /ready, memory, /locate and uploads at 1k / 100k / 1M.

    .venv/bin/python -m bench.scale [--sizes 1000,100000,1000000] [--config lite2-hybrid-384] [--out out/bench/scale]

For each size: a data dir seeded with synthetic codes (bench.seed, kept between runs), then a real
`geoloc serve`: the first start on the seeded rows (/ready, then the first /locate requests after it and the
resident memory: a start is ready only with the index kind its size calls for), /ready after a restart with
the snapshot and with the snapshot deleted, resident memory, /locate p50/p95 on real 1600 px photos steady
and right after an upload, the job time per upload, whether each uploaded photo is found first after its job
and gone from the next /locate once deleted, and how long a second API process on the same data dir takes to
see an upload. Prints the table and the ratios of
each size against the smallest, and writes them to OUT/scale.json and the scale section of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
import time
from pathlib import Path

import httpx

from app.engine.configs import DEFAULT_CONFIG
from bench.common import write_section
from bench.seed import placeholder, seed
from tools.server_process import ServerProcess, wait_job

REPO = Path(__file__).resolve().parents[1]
PENN = REPO.parent / "shared" / "data" / "penn-campus-gps" / "photos"
DOC = REPO / "docs" / "benchmarks.md"


def _ms(f) -> float:
    t0 = time.perf_counter()
    f()
    return (time.perf_counter() - t0) * 1000


def _rss_mb(client: httpx.Client) -> float:
    m = re.search(r"^process_resident_memory_bytes ([0-9.e+]+)$", client.get("/metrics").text, re.M)
    return float(m.group(1)) / 2**20 if m else float("nan")


def _locate(client: httpx.Client, photo: Path) -> float:
    return _ms(lambda: _candidates(client, photo.read_bytes()))


def _candidates(client: httpx.Client, data: bytes) -> list[int]:
    r = client.post("/locate", files=[("image", ("q.jpg", data, "image/jpeg"))], data={"top_k": 10})
    r.raise_for_status()
    return [c["reference_id"] for c in r.json()["candidates"]]


def _start(data: Path, models: Path, config: str, **kw) -> tuple[ServerProcess, float]:
    t0 = time.perf_counter()
    s = ServerProcess(data, models, config, api_key="bench", **kw)
    s.wait_ready(timeout=600)
    return s, time.perf_counter() - t0


def measure(size: int, root: Path, models: Path, config: str, photos: list[Path]) -> dict:
    data = root / f"n{size}"
    t0 = time.perf_counter()
    seeded = seed(data, size, models, config)
    out: dict = {"references": size, "seed_rows_per_s": seeded["rows_per_second"] if seeded["added"] else None}
    print(f"[{size:,d}] seeded in {time.perf_counter() - t0:.0f} s", flush=True)
    # First start (builds from SQLite if there is no snapshot yet, and the kind the size calls for), measured
    # from the first requests after /ready answers 200; clean stop (writes the final snapshot).
    s, out["ready_first_start_s"] = _start(data, models, config)
    first = [_locate(s.client, p) for p in photos]
    out["first_start_locate_p50_ms"] = statistics.median(first)
    out["first_start_rss_mb"] = _rss_mb(s.client)
    out["first_start_index"] = s.client.get("/ready").json()["index"]["float"]["kind"]
    s.stop()
    s, out["ready_with_snapshot_s"] = _start(data, models, config)
    out["rss_mb"] = _rss_mb(s.client)
    steady = [_locate(s.client, p) for p in photos]
    out["locate_p50_ms"] = statistics.median(steady)
    out["locate_p95_ms"] = sorted(steady)[int(0.95 * (len(steady) - 1))]
    second = ServerProcess(data, models, config, worker="none", api_key="bench")
    second.wait_ready(timeout=600)
    job_ms, after_ms, seen_ms, found_first, gone = [], [], [], 0, 0
    for n, photo in enumerate(photos[:5]):
        size_b = second.client.get("/ready").json()["index_size"]
        t_post = time.perf_counter()
        upload = placeholder(photo.read_bytes(), time.time_ns())
        r = s.client.post(
            "/references",
            files=[("image", (photo.name, upload, "image/jpeg"))],
            data={"lat": 39.95 + n * 1e-4, "lon": -75.19},
            headers={"X-API-Key": "bench"},
        )
        r.raise_for_status()
        body = r.json()
        if body["duplicates"][0]:
            continue
        wait_job(s.client, body["job_id"], timeout=600)
        job_ms.append((time.perf_counter() - t_post) * 1000)
        deadline = time.time() + 120
        while second.client.get("/ready").json()["index_size"] <= size_b and time.time() < deadline:
            time.sleep(0.01)
        seen_ms.append((time.perf_counter() - t_post) * 1000)
        after_ms.append(_locate(s.client, photos[-1 - n]))
        ref_id = body["reference_ids"][0]
        found_first += _candidates(s.client, upload)[:1] == [ref_id]
        s.client.delete(f"/references/{ref_id}", headers={"X-API-Key": "bench"}).raise_for_status()
        gone += ref_id not in _candidates(s.client, upload)
    out["uploads_found_first"] = f"{found_first} of {len(job_ms)}"
    out["deletes_gone_at_once"] = f"{gone} of {len(job_ms)}"
    out["job_p50_ms"] = statistics.median(job_ms) if job_ms else None
    out["locate_after_upload_p50_ms"] = statistics.median(after_ms) if after_ms else None
    out["second_process_sees_upload_p50_ms"] = statistics.median(seen_ms) if seen_ms else None
    out["snapshot_writes_during_uploads"] = int(
        float(re.search(r"^geoloc_snapshot_writes ([0-9.e+]+)$", s.client.get("/metrics").text, re.M).group(1))
    )
    second.stop()
    s.stop()
    for f in list(data.glob("*.faiss")) + [data / "index.json"]:
        f.unlink(missing_ok=True)
    s, out["ready_without_snapshot_s"] = _start(data, models, config)
    s.stop()
    print(json.dumps(out), flush=True)
    return out


def interleaved(sizes: list[int], root: Path, models: Path, config: str, photos: list[Path]) -> dict[int, dict]:
    """The same use cases in one process, size by size for each photo (the fairest comparison on a shared
    machine): locate through the core, and one upload accepted, encoded and completed (the job)."""
    from app.domain import LocateOptions, Upload
    from app.ingestion.worker import IngestWorker
    from app.usecases.service import GeolocService

    svcs = {n: GeolocService.open(root / f"n{n}", models, config) for n in sizes}
    out = {n: {"locate": [], "search": [], "job": []} for n in sizes}
    added: dict[int, list[int]] = {n: [] for n in sizes}
    for k, photo in enumerate(photos):
        data = photo.read_bytes()
        for n, svc in svcs.items():
            t0 = time.perf_counter()
            answer = svc.locate(data, LocateOptions(top_k=10))
            out[n]["locate"].append((time.perf_counter() - t0) * 1000)
            out[n]["search"].append(answer.timings_ms["search"])
            if k < 5:
                t0 = time.perf_counter()
                accepted = svc.accept([Upload(placeholder(data, time.time_ns()), photo.name, 39.95, -75.19)])
                IngestWorker(svc, batch_size=8).run_once()
                out[n]["job"].append((time.perf_counter() - t0) * 1000)
                added[n] += accepted.reference_ids
    for n, svc in svcs.items():  # the seeded data dirs stay as seeded: a later run's photos have no twins
        for ref_id in added[n]:
            svc.delete(ref_id)
        svc.close()
    return {n: {f"{k}_p50_ms": statistics.median(v) for k, v in d.items()} | {"references": n} for n, d in out.items()}


def interleaved_table(res: dict[int, dict]) -> str:
    sizes = sorted(res)
    base = res[sizes[0]]
    lines = [
        "| references | locate p50 (core) | search p50 | upload job p50 (accept + encode + complete) |",
        "|---|---|---|---|",
    ]
    for n in sizes:
        r = res[n]
        lines.append(
            f"| {n:,d} | {r['locate_p50_ms']:.0f} ({r['locate_p50_ms'] / base['locate_p50_ms']:.2f}x) | "
            f"{r['search_p50_ms']:.1f} | {r['job_p50_ms']:.0f} ({r['job_p50_ms'] / base['job_p50_ms']:.2f}x) |"
        )
    return "\n".join(lines)


def table(results: list[dict]) -> str:
    base = results[0]
    cols = [
        ("references", "{:,d}"),
        ("ready_first_start_s", "{:.1f}"),
        ("first_start_index", "{}"),
        ("first_start_locate_p50_ms", "{:.0f}"),
        ("first_start_rss_mb", "{:.0f}"),
        ("ready_with_snapshot_s", "{:.1f}"),
        ("ready_without_snapshot_s", "{:.1f}"),
        ("rss_mb", "{:.0f}"),
        ("locate_p50_ms", "{:.0f}"),
        ("locate_p95_ms", "{:.0f}"),
        ("locate_after_upload_p50_ms", "{:.0f}"),
        ("job_p50_ms", "{:.0f}"),
        ("second_process_sees_upload_p50_ms", "{:.0f}"),
        ("uploads_found_first", "{}"),
        ("deletes_gone_at_once", "{}"),
        ("snapshot_writes_during_uploads", "{}"),
    ]
    lines = ["| " + " | ".join(c for c, _ in cols) + " |", "|" + "---|" * len(cols)]
    for r in results:
        lines.append("| " + " | ".join(f.format(r[c]) if r.get(c) is not None else "-" for c, f in cols) + " |")
    lines.append("")
    for r in results[1:]:
        ratios = ", ".join(
            f"{c} {r[c] / base[c]:.2f}x"
            for c in ("first_start_locate_p50_ms", "job_p50_ms", "locate_after_upload_p50_ms", "locate_p50_ms")
            if r.get(c) and base.get(c)
        )
        more = r["references"] - base["references"]
        per_ref = ", ".join(
            f"{c} {(r[c] - base[c]) * 2**20 / more:+.0f} B per reference"
            for c in ("first_start_rss_mb", "rss_mb")
            if r.get(c) and base.get(c)
        )
        lines.append(f"- {r['references']:,d} against {base['references']:,d}: {ratios}; {per_ref}")
    return "\n".join(lines)


def write_doc(text: str, command: str) -> None:
    write_section(
        "scale",
        f"## The service at scale\n\n`{command}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
        "synthetic codes through bench/seed.py, real 1600 px photos for /locate and uploads; times in ms unless "
        "marked s; medians):\n\n" + text,
        DOC,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1000,100000,1000000")
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--root", type=Path, default=REPO / "out" / "bench" / "scale")
    ap.add_argument("--queries", type=int, default=20)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--skip-server", action="store_true", help="only the in-process comparison (seeded dirs)")
    args = ap.parse_args()
    photos = sorted(PENN.glob("*.jpg"))[: args.queries]
    sizes = [int(n) for n in args.sizes.split(",")]
    text = ""
    if not args.skip_server:
        results = [measure(n, args.root, args.models_dir, args.config, photos) for n in sizes]
        text = "On a real server (each size in turn):\n\n" + table(results) + "\n\n"
        (args.root / "scale.json").write_text(json.dumps(results, indent=1))
    inproc = interleaved(sizes, args.root, args.models_dir, args.config, photos)
    text += "In one process, interleaved photo by photo across the sizes (ratios against the smallest):\n\n"
    text += interleaved_table(inproc)
    (args.root / "scale-inprocess.json").write_text(json.dumps(inproc, indent=1))
    print(text)
    if not args.no_write:
        write_doc(text, ".venv/bin/python -m bench.scale " + " ".join(sys.argv[1:]))


if __name__ == "__main__":
    main()
