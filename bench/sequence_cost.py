"""What a sequence costs: one POST /locate/sequence of N photos against the same N photos sent to /locate one
by one, on one real server, interleaved round by round so both see the same machine.

The server serves a copy of a calibrated data dir (by default the demo collection `make demo` builds in
index/, with models/), so the sequence model runs (an uncalibrated collection skips it). The photos are the
demo's query photos (none of them, nor their crops, is in the collection), in EXIF time order as a caller
sends a sequence. Per round: the wall time of the sequence request and the sum of the N single requests'
wall times, and the server's peak RSS above its idle during each (sampled every 20 ms). Prints medians;
``--write`` puts them in docs/benchmarks.md.

    .venv/bin/python -m bench.sequence_cost --rounds 7
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from app.engine.configs import DEFAULT_CONFIG
from app.settings import usable_cpus
from app.usecases.sequence_inputs import exif_time, seconds
from bench.common import REPO, is_photo, penn_rows, write_section
from tools.process_memory import MiB, PeakRss, rss_bytes
from tools.server_process import ServerProcess


def query_photos(n: int) -> list[Path]:
    """``n`` of the manifest's query photos, in the order they were taken (EXIF, on the one clock the
    service reads a sequence's times by)."""
    photos = [r.image for r in penn_rows() if r.split == "query" and is_photo(r)]
    times = {p: exif_time(p.read_bytes()) for p in photos}
    timed = [p for p in photos if times[p] is not None]
    if len(timed) < n:
        raise SystemExit(f"only {len(timed)} query photos carry an EXIF time; asked for {n}")
    secs = seconds([times[p] for p in timed])
    return [p for _, p in sorted(zip(secs, timed, strict=True))][:n]


def files(photos: list[Path]) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [("image", (p.name, p.read_bytes(), "image/jpeg")) for p in photos]


def timed_peak(pid: int, send) -> tuple[float, int]:
    """Seconds ``send()`` took, and the server's largest RSS meanwhile."""
    with PeakRss(pid, every_s=0.02) as sampler:
        t0 = time.perf_counter()
        send()
        seconds = time.perf_counter() - t0
    return seconds, sampler.peak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", type=Path, default=REPO / "index", help="a calibrated data dir (copied)")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--config", default=DEFAULT_CONFIG, help="the data dir's configuration")
    ap.add_argument("--photos", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--write", action="store_true", help="write the figures into docs/benchmarks.md")
    args = ap.parse_args()
    if not (args.data_dir / "references.sqlite").exists():
        raise SystemExit(f"{args.data_dir} holds no collection: run `make demo` first (or give --data-dir)")

    photos = query_photos(args.photos)
    body = files(photos)
    seq_s, singles_s, seq_peak, singles_peak = [], [], [], []
    with tempfile.TemporaryDirectory(prefix="sequence-cost-") as tmp:
        data = Path(tmp) / "data"
        shutil.copytree(args.data_dir, data, ignore=shutil.ignore_patterns("worker.lock", "*.lock"))
        with ServerProcess(data, args.models_dir, args.config) as server:
            pid = server.proc.pid
            client = server.client
            client.timeout = 600

            def sequence() -> None:
                r = client.post("/locate/sequence", files=body)
                r.raise_for_status()
                if r.json()["note"]:
                    raise SystemExit(f"the sequence model did not run: {r.json()['note']}")

            def singles() -> None:
                for f in body:
                    client.post("/locate", files=[f]).raise_for_status()

            sequence()  # warm: models loaded, first-call allocations done
            singles()
            time.sleep(1.0)
            idle = rss_bytes(pid)
            for k in range(args.rounds):
                order = (sequence, singles) if k % 2 == 0 else (singles, sequence)
                for send in order:
                    seconds, peak = timed_peak(pid, send)
                    (seq_s if send is sequence else singles_s).append(seconds)
                    (seq_peak if send is sequence else singles_peak).append(peak - idle)
                print(f"  round {k}: sequence {seq_s[-1]:.2f} s, singles {singles_s[-1]:.2f} s", flush=True)

    ratios = [a / b for a, b in zip(seq_s, singles_s, strict=True)]
    med = statistics.median
    lines = [
        "## A sequence against its photos one by one",
        "",
        f"`python -m bench.sequence_cost --rounds {args.rounds}` ({args.config}, the demo collection, "
        f"{usable_cpus()} CPUs): one `POST /locate/sequence` of {args.photos} query photos (EXIF time order) against "
        "the same photos sent to `/locate` one by one, interleaved on one real server; its RSS over idle.",
        "",
        "| request | median s | peak RSS rise, median / largest MB |",
        "|---|---|---|",
        f"| `/locate/sequence`, {args.photos} photos | {med(seq_s):.2f} | {med(seq_peak) / MiB:.0f} / "
        f"{max(seq_peak) / MiB:.0f} |",
        f"| {args.photos} x `/locate` | {med(singles_s):.2f} | {med(singles_peak) / MiB:.0f} / "
        f"{max(singles_peak) / MiB:.0f} |",
        "",
        f"Sequence / singles: {med(ratios):.2f}x (median of rounds; {min(ratios):.2f}-{max(ratios):.2f}x).",
    ]
    text = "\n".join(lines)
    print("\n" + text)
    if args.write:
        write_section("sequence-cost", text)


if __name__ == "__main__":
    main()
