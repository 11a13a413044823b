"""How the ``ivf-rabitq`` re-rank reads its float codes: ``pread`` (``FloatCodeTable``) against a memory map.

    .venv/bin/python -m bench.rerank_reads --n 1000000 --repeats 2

Writes ``--n`` random 256-float codes in the table's file layout (once, ``--path``), then, each way in its
own process (so that one's resident pages do not count in the other's), reads 100 random codes and scores
them against a query ``--reads`` times, as one query's re-rank does: the read's median and 90th percentile,
and the process's RssFile (the file's pages resident in it) after 3, 100 and all reads. The two ways
alternate ``--repeats`` times.
"""

from __future__ import annotations

import argparse
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DIM = 256


def _status_mb(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(field)


def write_codes(path: Path, n: int) -> None:
    rng = np.random.default_rng(0)
    with open(path, "wb") as f:
        f.write(struct.pack("<QQ", n, DIM))
        f.write(np.arange(n, dtype=np.int64).tobytes())
        for lo in range(0, n, 65536):
            f.write(rng.standard_normal((min(65536, n - lo), DIM)).astype(np.float32).tobytes())


def one_way(how: str, path: Path, n: int, reads: int) -> None:
    """The reads of one way, in this process; prints its line."""
    from app.engine.index.float_code_table import FloatCodeTable

    if how == "pread":
        get = FloatCodeTable.read(path, 0).get
    else:
        codes = np.memmap(path, np.float32, "r", offset=16 + 8 * n, shape=(n, DIM))

        def get(ids):
            return codes[np.sort(ids)]

    rng = np.random.default_rng(1)
    q = rng.standard_normal(DIM).astype(np.float32)
    before, resident, ms = _status_mb("RssFile"), {}, []
    for i in range(reads):
        ids = rng.choice(n, 100, replace=False)
        t = time.perf_counter()
        _ = get(ids) @ q
        ms.append((time.perf_counter() - t) * 1e3)
        if i + 1 in (3, 100, reads):
            resident[i + 1] = _status_mb("RssFile") - before
    print(
        f"{how:5s}: 100 codes read and scored, p50 {np.median(ms):.3f} ms, p90 {np.percentile(ms, 90):.3f} ms; "
        + ", ".join(f"RssFile +{mb:.0f} MB after {k} reads" for k, mb in resident.items()),
        flush=True,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--reads", type=int, default=3000)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--path", type=Path, default=Path("/tmp/geoloc-rerank-codes.bin"))
    ap.add_argument("--one", choices=["pread", "mmap"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        one_way(args.one, args.path, args.n, args.reads)
        return
    expected = 16 + args.n * (8 + 4 * DIM)
    if not args.path.exists() or args.path.stat().st_size != expected:
        write_codes(args.path, args.n)
    for rep in range(args.repeats):
        for how in ("pread", "mmap") if rep % 2 == 0 else ("mmap", "pread"):
            cmd = [sys.executable, "-m", "bench.rerank_reads", "--one", how, "--path", str(args.path)]
            subprocess.run([*cmd, "--n", str(args.n), "--reads", str(args.reads)], check=True)


if __name__ == "__main__":
    main()
