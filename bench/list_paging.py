"""GET /references pages at 10^6 rows: by position (``offset``, with ``total``) against by id (``after`` /
``before``), on SQLite and on PostgreSQL, in one process.

Run: ``python -m bench.list_paging --refs 1000000`` (``--no-postgres`` for SQLite alone; PostgreSQL is a
throw-away server of its own, as in ``bench.pg_catchup``). The rows are written straight into the store's
``refs`` table (1 KB float code each, like the default configuration's; no image files: listing never reads
them), then each page is read ``--reps`` times through the store methods the endpoint calls
(``ReferenceStore.list`` and ``ReferenceStore.page``) and the medians printed, with the ratio of every page
to the first page read the same way. Never part of a timed test.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from app.storage.settings import StorageSettings
from app.storage.store import ReferenceStore
from tools.postgres_server import PostgresServer

LIMIT = 50
COLUMNS = ("sha256", "lat", "lon", "created_at", "float_code", "status")


def _rows(start: int, n: int, rng: np.random.Generator):
    code = rng.standard_normal(256).astype(np.float32).tobytes()
    lats, lons = rng.uniform(39.9, 40.0, n), rng.uniform(-75.2, -75.1, n)
    for i in range(n):
        yield (f"{start + i:064x}", float(lats[i]), float(lons[i]), "2026-11-25T00:00:00Z", code, "indexed")


def _seed(store: ReferenceStore, refs: int, batch: int = 50_000) -> float:
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for start in range(0, refs, batch):
        rows = list(_rows(start, min(batch, refs - start), rng))
        with store.transaction() as db:
            store.backend.copy_rows(db, "refs", COLUMNS, rows)
    if store.engine == "postgres":
        store.db.execute("ANALYZE refs")
    return time.perf_counter() - t0


def _median_ms(read: Callable[[], object], reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        read()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def measure(store: ReferenceStore, refs: int, reps: int) -> dict[str, float]:
    middle_id = refs // 2
    cases: dict[str, Callable[[], object]] = {
        "first page by offset (+ total)": lambda: store.list(0, LIMIT),
        "middle page by offset (+ total)": lambda: store.list(refs // 2, LIMIT),
        "last page by offset (+ total)": lambda: store.list(refs - LIMIT, LIMIT),
        "first page by id": lambda: store.page(after=0, limit=LIMIT),
        "middle page by id": lambda: store.page(after=middle_id, limit=LIMIT),
        "last page by id": lambda: store.page(before=2**63 - 1, limit=LIMIT),
        "total=true (count every row)": lambda: store.count_in(),
    }
    page = store.page(after=middle_id, limit=LIMIT)
    assert len(page.items) == LIMIT and page.items[0].id == middle_id + 1, page.items[:1]
    return {name: _median_ms(read, reps) for name, read in cases.items()}


def _one_engine(data: Path, refs: int, reps: int) -> dict:
    store = ReferenceStore(data, backend=StorageSettings().backend(data))
    try:
        seed_s = _seed(store, refs)
        print(f"[{store.engine}] {refs:,d} rows written in {seed_s:.0f} s", flush=True)
        return measure(store, refs, reps)
    finally:
        store.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--refs", type=int, default=1_000_000)
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--no-postgres", action="store_true")
    args = ap.parse_args()
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="geoloc-bench-list-") as tmp:
        os.environ.pop("GEOLOC_DATABASE_URL", None)
        results["sqlite"] = _one_engine(Path(tmp) / "sqlite", args.refs, args.reps)
        if not args.no_postgres:
            server = PostgresServer().start()
            try:
                os.environ["GEOLOC_DATABASE_URL"] = server.create_database()
                results["postgres"] = _one_engine(Path(tmp) / "postgres", args.refs, args.reps)
            finally:
                os.environ.pop("GEOLOC_DATABASE_URL", None)
                server.stop()
    engines = list(results)
    print(f"\n{args.refs:,d} references, pages of {LIMIT}, medians of {args.reps} reads")
    print("(ms; in brackets: against the first page by id on the same engine)")
    print("| page | " + " | ".join(engines) + " |")
    print("|---|" + "---|" * len(engines))
    for case in results[engines[0]]:
        cells = []
        for e in engines:
            ms, base = results[e][case], results[e]["first page by id"]
            cells.append(f"{ms:.2f} ({ms / base:.0f}x)")
        print(f"| {case} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
