"""How long `geoloc library scan` takes on a large folder, and its memory: N small photos without GPS
(penn-campus-gps's 224 px crops, copied under distinct names) located against penn's geotagged photos.

    .venv/bin/python -m bench.library_scan [--files 3000] [--baseline DIR]

``--baseline DIR``: a checkout of another commit (``git worktree add DIR REV``); its scan runs on the same
folder and collection, interleaved with this checkout's (baseline, this, baseline, this ... for
``--repeats``), so both see the same machine. Prints the wall time, photos per second and the peak RSS of
each run, the medians and the ratio to the baseline."""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import MANIFEST, REPO, machine
from tools.process_memory import MiB, PeakRss

PENN = REPO.parent / "shared" / "data" / "penn-campus-gps"
CONFIG = "lite2-hybrid-384"


def make_folder(dest: Path, files: int) -> Path:
    """``files`` photos without GPS in two levels of sub-folders (100 per folder), cycling over the crops."""
    crops = sorted((PENN / "crops").glob("*.jpg"))
    for n in range(files):
        sub = dest / f"d{n // 1000:02d}" / f"s{(n // 100) % 10}"
        sub.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(crops[n % len(crops)], sub / f"p{n:06d}.jpg")
    return dest


def collection(dest: Path) -> Path:
    """A data dir holding the manifest's ``db`` rows (the references the folder is located against)."""
    args = ["ingest", "--manifest", str(MANIFEST), "--split", "db", "--config", CONFIG, "--data-dir", str(dest)]
    subprocess.run([sys.executable, "-m", "app.cli", *args], check=True, capture_output=True, cwd=REPO)
    return dest


def scan_once(code: Path, folder: Path, data: Path, workers: int) -> tuple[float, float]:
    """(seconds, peak RSS MiB) of one scan of ``folder`` into a copy of ``data``, run by the code in ``code``."""
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "data"
        shutil.copytree(data, copy)
        args = ["library", "scan", str(folder), "--data-dir", str(copy), "--config", CONFIG,
                "--models-dir", str(REPO / "models"), "--workers", str(workers)]  # fmt: skip
        start = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "app.cli", *args], cwd=code, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)  # fmt: skip
        with PeakRss(proc.pid) as peak:
            out, _ = proc.communicate()
        seconds = time.perf_counter() - start
        if proc.returncode != 0:
            raise SystemExit(f"scan failed ({proc.returncode}): {out[-2000:]}")
        return seconds, peak.peak / MiB


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=3000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--baseline", type=Path, help="a checkout of another commit, run interleaved")
    args = ap.parse_args()
    if args.files < 1 or args.repeats < 1:
        ap.error("--files and --repeats must be at least 1")
    runs: dict[str, list[tuple[float, float]]] = {"baseline": [], "this": []}
    with tempfile.TemporaryDirectory() as tmp:
        folder = make_folder(Path(tmp) / "library", args.files)
        data = collection(Path(tmp) / "data")
        for _ in range(args.repeats):
            for name, code in (("baseline", args.baseline), ("this", REPO)):
                if code is None:
                    continue
                runs[name].append(scan_once(code.resolve(), folder, data, args.workers))
                s, mb = runs[name][-1]
                print(f"{name}: {s:.1f} s, {args.files / s:.1f} photos/s, peak RSS {mb:.0f} MiB", flush=True)
    print(f"{machine()}; {args.files} photos, {args.workers} threads")
    for name, got in runs.items():
        if got:
            s = statistics.median(t for t, _ in got)
            mb = statistics.median(m for _, m in got)
            print(f"median {name}: {s:.1f} s ({args.files / s:.1f} photos/s), peak RSS {mb:.0f} MiB")
    if runs["baseline"] and runs["this"]:
        ratio = statistics.median(t for t, _ in runs["this"]) / statistics.median(t for t, _ in runs["baseline"])
        print(f"time ratio this / baseline: {ratio:.3f}")


if __name__ == "__main__":
    main()
