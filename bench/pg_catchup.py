"""The store on PostgreSQL against SQLite, in one process: what a replica pays to catch up on one change, what
a cold start pays to read every code, and what the rows take on disk (the README's sizing note).

Run: ``python -m bench.pg_catchup --refs 100000`` (starts a throw-away PostgreSQL server of its own with
``tools.postgres_server``: Debian's ``postgresql`` package, as the tests do). Both stores are seeded with the
same synthetic pre-encoded references (random 256-float codes: the default configuration's size, 1 KB each)
through the bulk path (``add_many``: COPY on PostgreSQL). Then, ``--changes`` times: one change is committed
on one connection and another connection, holding the previous version, reads the head and the change
(``head`` + ``changes_since``: exactly what ``Collection.catch_up`` asks of the store). Medians, and the
ratio PostgreSQL / SQLite. Never part of a timed test.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from app.storage.store import NewReference, ReferenceStore
from tools.postgres_server import PostgresServer

FLOAT_DIM = 256  # the default configuration's float code (hybrid): 1 KB per reference


def _items(rng: np.random.Generator, start: int, n: int) -> list[NewReference]:
    return [
        NewReference(
            f"synthetic-{start + i}".encode(),  # distinct bytes; no image is read back here
            "jpg",
            float(rng.uniform(39.9, 40.0)),
            float(rng.uniform(-75.2, -75.1)),
            float_code=rng.standard_normal(FLOAT_DIM).astype(np.float32),
        )
        for i in range(n)
    ]


def _seed(data: Path, refs: int, batch: int) -> tuple[ReferenceStore, float]:
    store = ReferenceStore(data)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for start in range(0, refs, batch):
        store.add_many(_items(rng, start, min(batch, refs - start)))
    return store, time.perf_counter() - t0


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


def _cold_start_s(store: ReferenceStore) -> tuple[float, int]:
    t0 = time.perf_counter()
    _, ids, fcodes, _ = store.all_codes()
    codes = np.frombuffer(b"".join(fcodes), np.float32).reshape(len(ids), FLOAT_DIM)
    return time.perf_counter() - t0, len(codes)


def _one_engine(name: str, data: Path, args) -> dict:
    store, seed_s = _seed(data, args.refs, args.batch)
    reader = ReferenceStore(data)
    cold_s, n = _cold_start_s(reader)
    catch = _catch_up_ms(store, reader, args.changes)
    out = {
        "engine": name,
        "seed_rows_per_s": args.refs / seed_s,
        "cold_read_s": cold_s,
        "codes_read": n,
        "catch_up_ms_median": statistics.median(catch),
    }
    if name == "postgres":
        sizes = dict(
            store.db.execute(
                "SELECT relname, pg_total_relation_size(oid) FROM pg_class WHERE relname IN ('refs', 'changes')"
            ).fetchall()
        )
        out["refs_bytes_per_row"] = sizes["refs"] / (args.refs + args.changes)
        out["changes_bytes_per_row"] = sizes["changes"] / (args.refs + args.changes)
    else:
        out["sqlite_bytes_per_row"] = (data / "references.sqlite").stat().st_size / (args.refs + args.changes)
    store.close()
    reader.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--refs", type=int, default=100_000)
    ap.add_argument("--changes", type=int, default=200)
    ap.add_argument("--batch", type=int, default=5_000)
    args = ap.parse_args()
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
    print(f"{args.refs} references, {args.changes} changes, codes of {FLOAT_DIM} floats")
    for key in ("seed_rows_per_s", "cold_read_s", "catch_up_ms_median"):
        ratio = postgres[key] / sqlite[key]
        print(f"{key:>20}: sqlite {sqlite[key]:10.3f}  postgres {postgres[key]:10.3f}  ratio {ratio:5.2f}")
    print(
        f"on disk per reference: sqlite {sqlite['sqlite_bytes_per_row']:.0f} B; postgres refs "
        f"{postgres['refs_bytes_per_row']:.0f} B + change log {postgres['changes_bytes_per_row']:.0f} B"
    )


if __name__ == "__main__":
    main()
