"""The store on PostgreSQL against SQLite, in one process: what a replica pays to catch up on one change, what
a cold start pays to read every code, what the rows take on disk (the sizing note of docs/operations.md), and whether a
query the service runs per request or per change grows with the collection.

Run: ``python -m bench.pg_catchup --refs 1000000`` (starts a throw-away PostgreSQL server of its own with
``tools.postgres_server``: Debian's ``postgresql`` package, as the tests do). Both stores get the same
synthetic pre-encoded references (random 256-float codes: the default configuration's size, 1 KB each):
the first ``--add-rows`` through the store's bulk path (``add_many``: image files written and synced, COPY
on PostgreSQL), which gives the insert rate; the rest straight into the store's own tables, the rows and
their change log entries as ``add_many`` writes them, in big batches (COPY on PostgreSQL, one
``executemany`` on SQLite), without image files: nothing measured here reads an image, and writing and
syncing 10^6 files per engine was where a 10^6 run spent its time (see docs/benchmarks.md).

What is measured is the store's real code, as the service runs it: the cold start is ``code_stream`` (the
bulk read a replica starting without a snapshot makes, in a process started for it, with that process's
peak resident memory); then,
``--changes`` times, one change is committed on one connection and another connection, holding the
previous version, reads ``head`` + ``changes_since`` (exactly what ``Collection.catch_up`` asks of the
store when the ``ChangeListener`` wakes it). Last, the per-request and per-change reads (``head``,
``changes_since``, ``get_many``, ``extent``, ``count('pending')``, ``pending``, ``get``) are timed at this
size and their plans printed (``EXPLAIN ANALYZE`` on PostgreSQL, ``EXPLAIN QUERY PLAN`` on SQLite) with
any full scan flagged. Medians, and the ratio PostgreSQL / SQLite. Never part of a timed test.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from app.storage.postgres import _bind, translate
from app.storage.settings import StorageSettings
from app.storage.store import NewReference, ReferenceStore
from bench.scale_codes import unit_rows
from tools.postgres_server import PostgresServer

FLOAT_DIM = 256  # the default configuration's float code (hybrid): 1 KB per reference
#: The columns ``add_many`` fills for a pre-encoded reference (``StorageBackend.insert_refs``).
SEED_COLS = ("sha256", "lat", "lon", "image_ext", "created_at", "float_code", "status")


def _sha(n: int) -> str:
    return hashlib.sha256(f"synthetic-{n}".encode()).hexdigest()


def _items(rng: np.random.Generator, start: int, n: int) -> list[NewReference]:
    return [
        NewReference(
            f"synthetic-{start + i}".encode(),  # distinct bytes; no image is read back here
            "jpg",
            float(rng.uniform(39.9, 40.0)),
            float(rng.uniform(-75.2, -75.1)),
            float_code=unit_rows(rng.standard_normal((1, FLOAT_DIM), dtype=np.float32))[0],
        )
        for i in range(n)
    ]


def _status_mb(field: str) -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(field + ":")) / 1024


def _rss_mb() -> float:
    return _status_mb("VmRSS")


def _peak_rss_mb() -> float:
    return _status_mb("VmHWM")


def _seed_rows(store: ReferenceStore, rng: np.random.Generator, start: int, n: int) -> None:
    """``n`` indexed rows and their 'add' change log entries in one transaction, as ``add_many`` writes them,
    by the engine's bulk path (COPY on PostgreSQL): the rows of a pre-encoded bulk load, without images."""
    # unit rows, as the pipeline's codes are: a raw Gaussian row has norm about 16, and its inner products
    # would outrank a real photo's own code
    codes = unit_rows(rng.standard_normal((n, FLOAT_DIM), dtype=np.float32))
    lats, lons = rng.uniform(39.9, 40.0, n), rng.uniform(-75.2, -75.1, n)
    now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    rows = [
        (_sha(start + i), float(lats[i]), float(lons[i]), "jpg", now, codes[i].tobytes(), "indexed") for i in range(n)
    ]
    with store.transaction() as db:
        high = db.execute("SELECT COALESCE(MAX(id), 0) FROM refs").fetchone()[0]
        store.backend.copy_rows(db, "refs", SEED_COLS, rows)
        db.execute("INSERT INTO changes(ref_id, op) SELECT id, 'add' FROM refs WHERE id > ? ORDER BY id", (high,))


def _seed(data: Path, refs: int, add_rows: int, batch: int, seed_batch: int) -> tuple[ReferenceStore, float, float]:
    """The store with ``refs`` references; returns it, the ``add_many`` rate (rows/s) and the seed's time."""
    store = ReferenceStore(data, backend=StorageSettings().backend(data))
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    added = min(add_rows, refs)
    for start in range(0, added, batch):
        store.add_many(_items(rng, start, min(batch, added - start)))
    add_rate = added / (time.perf_counter() - t0) if added else float("nan")
    for start in range(added, refs, seed_batch):
        _seed_rows(store, rng, start, min(seed_batch, refs - start))
    if store.engine == "postgres":  # what add_many's after_bulk_insert does after a load
        store.db.execute("ANALYZE refs, changes")
    return store, add_rate, time.perf_counter() - t0


def _catch_up_ms(writer: ReferenceStore, reader: ReferenceStore, changes: int) -> list[float]:
    rng = np.random.default_rng(1)
    version = reader.head()[0]
    out = []
    for n in range(changes):
        writer.add_many(_items(rng, 10**9 + n, 1))
        t0 = time.perf_counter()
        head, _ = reader.head()
        got = reader.changes_since(version)
        out.append((time.perf_counter() - t0) * 1e3)
        assert head == version + 1 and len(got) == 1, (head, version, len(got))
        version = head
    return out


def _cold_start(data: Path) -> dict:
    """The bulk read a replica starting cold makes (``code_stream``, chunk by chunk), in a fresh
    process as a replica would run it: seconds, codes read, and that process's resident memory before the
    read and at its peak."""
    out = subprocess.run(
        [sys.executable, "-m", "bench.pg_catchup", "--cold-read", str(data)],
        capture_output=True, text=True, check=True, env=os.environ.copy(),
    )  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def _cold_read(data: Path) -> None:
    """``--cold-read DIR``: the child process of ``_cold_start``; prints one line of JSON."""
    store = ReferenceStore(data, read_only=True, backend=StorageSettings().backend(data))
    base = _rss_mb()
    t0 = time.perf_counter()
    with store.code_stream() as stream:
        n = sum(len(c.ids) for c in stream.chunks)
    took = time.perf_counter() - t0
    print(json.dumps({"s": took, "n": n, "base_mb": base, "peak_mb": _peak_rss_mb()}))


def _plan(store: ReferenceStore, sql: str, params) -> list[str]:
    if store.engine == "postgres":
        text, lists = translate(sql)
        rows = store.db.raw.execute("EXPLAIN (ANALYZE, COSTS OFF, TIMING OFF) " + text, _bind(params, lists))
        return [r[0] for r in rows.fetchall()]
    return [r[-1] for r in store.db.execute("EXPLAIN QUERY PLAN " + sql, params or ()).fetchall()]


def _full_scan(store: ReferenceStore, plan: list[str]) -> bool:
    """A plan step that reads a whole table: a sequential scan on PostgreSQL, ``SCAN <table>`` with no index
    on SQLite (a ``SCAN`` of a json_each list or an index's ``USING ... INDEX`` is not one)."""
    if store.engine == "postgres":
        return any("Seq Scan on refs" in p or "Seq Scan on changes" in p for p in plan)
    return any(
        p.startswith("SCAN ") and "INDEX" not in p and "json_each" not in p and "CONSTANT ROW" not in p for p in plan
    )


class _Recorder:
    """The store's connection, recording the SELECTs issued through it (to explain them afterwards)."""

    def __init__(self, conn) -> None:
        self.conn = conn
        self.seen: list[tuple[str, object]] = []

    def execute(self, sql: str, params=None):
        if sql.lstrip().upper().startswith("SELECT"):
            self.seen.append((sql, params))
        return self.conn.execute(sql) if params is None else self.conn.execute(sql, params)

    def __getattr__(self, name: str):
        return getattr(self.conn, name)


def _service_queries(store: ReferenceStore, repeat: int) -> dict[str, tuple[float, bool, list[str]]]:
    """What the service asks per request (/locate: head, get_many, extent; /metrics: count('pending');
    GET /references/{id}) and per change (head + changes_since; the worker's pending): median ms over
    ``repeat`` calls, whether any plan reads a whole table, and the plans (statements recorded as the real
    methods issue them)."""
    version = store.head()[0]
    ids = [int(i) for i in np.linspace(1, version, 10)]
    calls: dict[str, Callable[[], object]] = {
        "head": store.head,
        "changes_since(last)": lambda: store.changes_since(version - 1),
        "get_many(10)": lambda: store.get_many(ids),
        "get(1)": lambda: store.get(ids[len(ids) // 2]),
        "extent": store.extent,
        "count('pending')": lambda: store.count("pending"),
        "pending(8)": lambda: store.pending(8),
    }
    out = {}
    for name, call in calls.items():
        real = store.database.db  # the connection every part of the store reads through
        store.database.db = recorder = _Recorder(real)
        try:
            call()
        finally:
            store.database.db = real
        ms = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            call()
            ms.append((time.perf_counter() - t0) * 1e3)
        plans = [line for sql, params in recorder.seen for line in _plan(store, sql, params)]
        out[name] = (statistics.median(ms), _full_scan(store, plans), plans)
    return out


def _one_engine(name: str, data: Path, args) -> dict:
    store, add_rate, seed_s = _seed(data, args.refs, args.add_rows, args.batch, args.seed_batch)
    print(f"{name}: {args.refs} references stored in {seed_s:.0f} s", flush=True)
    cold = _cold_start(data)
    assert cold["n"] == args.refs, cold
    reader = ReferenceStore(data, backend=StorageSettings().backend(data))
    catch = _catch_up_ms(store, reader, args.changes)
    out = {
        "engine": name,
        "add_many_rows_per_s": add_rate,
        "cold_read_s": cold["s"],
        "cold_read_peak_mb": cold["peak_mb"] - cold["base_mb"],
        "codes_read": cold["n"],
        "catch_up_ms_median": statistics.median(catch),
        "catch_up_ms_p95": float(np.percentile(catch, 95)),
        "queries": _service_queries(reader, args.repeat),
    }
    total = args.refs + args.changes
    if name == "postgres":
        sizes = dict(
            store.db.execute(
                "SELECT relname, pg_total_relation_size(oid) FROM pg_class WHERE relname IN ('refs', 'changes')"
            ).fetchall()
        )
        out["refs_bytes_per_row"] = sizes["refs"] / total
        out["changes_bytes_per_row"] = sizes["changes"] / total
    reader.close()
    store.close()  # SQLite: the WAL checkpointed into the main file first
    if name == "sqlite":
        out["sqlite_bytes_per_row"] = (data / "references.sqlite").stat().st_size / total
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--refs", type=int, default=100_000)
    ap.add_argument("--changes", type=int, default=200)
    ap.add_argument("--add-rows", type=int, default=20_000, help="of --refs, stored through add_many (timed)")
    ap.add_argument("--batch", type=int, default=5_000, help="add_many's batch")
    ap.add_argument("--seed-batch", type=int, default=50_000, help="rows per transaction of the rest")
    ap.add_argument("--repeat", type=int, default=50, help="calls per service query timed")
    ap.add_argument("--plans", action="store_true", help="print every query plan, not only flagged ones")
    ap.add_argument("--cold-read", type=Path, help=argparse.SUPPRESS)  # the cold read's child process
    args = ap.parse_args()
    if args.cold_read:
        _cold_read(args.cold_read)
        return
    server = PostgresServer().start()
    try:
        with tempfile.TemporaryDirectory(prefix="geoloc-bench-pg-") as tmp:
            os.environ.pop("GEOLOC_DATABASE_URL", None)
            sqlite = _one_engine("sqlite", Path(tmp) / "sqlite", args)
            os.environ["GEOLOC_DATABASE_URL"] = server.create_database()
            postgres = _one_engine("postgres", Path(tmp) / "postgres", args)
    finally:
        os.environ.pop("GEOLOC_DATABASE_URL", None)
        server.stop()
    print(f"{args.refs} references ({args.add_rows} through add_many), {args.changes} changes, {FLOAT_DIM} floats")
    for key in ("add_many_rows_per_s", "cold_read_s", "cold_read_peak_mb", "catch_up_ms_median", "catch_up_ms_p95"):
        ratio = postgres[key] / sqlite[key]
        print(f"{key:>20}: sqlite {sqlite[key]:10.3f}  postgres {postgres[key]:10.3f}  ratio {ratio:5.2f}")
    print(
        f"on disk per reference: sqlite {sqlite['sqlite_bytes_per_row']:.0f} B; postgres refs "
        f"{postgres['refs_bytes_per_row']:.0f} B + change log {postgres['changes_bytes_per_row']:.0f} B"
    )
    print("service queries, median ms (a full scan of refs or changes flagged):")
    for q in sqlite["queries"]:
        (s_ms, s_scan, s_plan), (p_ms, p_scan, p_plan) = sqlite["queries"][q], postgres["queries"][q]
        flag = " ".join(f for f, on in (("SQLITE-FULL-SCAN", s_scan), ("PG-SEQ-SCAN", p_scan)) if on)
        print(f"{q:>20}: sqlite {s_ms:8.3f}  postgres {p_ms:8.3f}  {flag}")
        if args.plans or s_scan or p_scan:
            for engine, plan in (("sqlite", s_plan), ("postgres", p_plan)):
                for line in plan:
                    print(f"{'':>22}{engine}: {line}")


if __name__ == "__main__":
    main()
