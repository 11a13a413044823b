"""What a re-fit's generation switch costs as the collection grows, and what a request pays for generations.

For each size N: a data dir of N indexed references with random 256-float codes (the size `hybrid` stores)
and a complete ``next_codes`` table, then (1) the median of ``ReferenceStore.head()``, the one read every
request makes (index version and generation together), before and after the switch; (2) the switch
transaction itself (re-check that no reference misses its code, rename the table, meta), during which other
writers wait for SQLite's write lock; (3) the copy of the codes into ``refs`` afterwards, in transactions of
5,000 rows (the longest one is what a writer may wait); (4) the cursor read of the re-index loop (the next
batch of references without a new code, half of them done). Ratios are against
the smallest N, in this process.

    python -m bench.switch_scaling --sizes 10000 100000
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from app.storage.store import ReferenceStore


def _fill(store: ReferenceStore, n: int, dim: int) -> None:
    rng = np.random.default_rng(0)
    with store.transaction() as db:
        for start in range(0, n, 10_000):
            m = min(10_000, n - start)
            codes = rng.standard_normal((m, dim)).astype(np.float32)
            db.executemany(
                "INSERT INTO refs(sha256, lat, lon, image_ext, created_at, float_code, status) "
                "VALUES(?,?,?,?,?,?,'indexed')",
                [(f"{start + i:064x}", 39.95, -75.19, "jpg", "now", codes[i].tobytes()) for i in range(m)],
            )
            db.executemany("INSERT INTO changes(ref_id, op) VALUES(?, 'add')", [(start + i + 1,) for i in range(m)])
            db.executemany(
                "INSERT INTO next_codes(ref_id, float_code) VALUES(?, ?)",
                [(start + i + 1, (codes[i] * 2).tobytes()) for i in range(m)],
            )


def _median_ms(fn, repeat: int = 200) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def measure(n: int, dim: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        store = ReferenceStore(Path(tmp))
        _fill(store, n, dim)
        target = {"generation": 1, "pipeline": "pipelines/x-g1", "config": "x", "fp": "x:1"}
        store.set_meta("reindex_target", json.dumps(target, sort_keys=True))
        head_before = _median_ms(store.head)
        with store.transaction() as db:  # half re-encoded: the loop's next read is at the half-way cursor
            db.execute("DELETE FROM next_codes WHERE ref_id > ?", (n // 2,))
        cursor = _median_ms(lambda: store.reindex_todo(256, n // 2), 20)
        with store.transaction() as db:
            db.execute(
                "INSERT INTO next_codes(ref_id, float_code) SELECT id, float_code FROM refs WHERE id > ?", (n // 2,)
            )
        t0 = time.perf_counter()
        assert store.switch_generation(target, "x:1", "x") == 1
        switch_s = time.perf_counter() - t0
        head_after = _median_ms(store.head)
        copies = []
        while True:
            t0 = time.perf_counter()
            if not store.migrate_switched():
                break
            copies.append(time.perf_counter() - t0)
        store.close()
    return {
        "n": n,
        "head_before": head_before,
        "head_after": head_after,
        "cursor": cursor,
        "switch": switch_s,
        "copy": sum(copies),
        "copy_txn": max(copies),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--dim", type=int, default=256)
    args = ap.parse_args()
    rows = [measure(n, args.dim) for n in args.sizes]
    base = rows[0]
    print(
        "| references | head() ms before / after switch | ratio | re-index cursor read ms | switch s | ratio "
        "| copy into refs s (longest transaction s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['n']:,} | {r['head_before']:.3f} / {r['head_after']:.3f} | "
            f"{r['head_after'] / base['head_after']:.2f} | {r['cursor']:.3f} | {r['switch']:.2f} | "
            f"{r['switch'] / base['switch']:.1f} | {r['copy']:.1f} ({r['copy_txn']:.2f}) |"
        )


if __name__ == "__main__":
    main()
