"""What a region search costs on the ``milvus`` kind and what it finds, by how many references the region's
box holds: the replica's exact scoring of every code in the box (what ``MilvusIndex`` does up to
``EXACT_FILTERED`` references) against Milvus's own HNSW search with the filter applied inside it.

    .venv/bin/python -m bench.milvus_region --codes 20000 --sides 0.05,0.1,0.2,0.4,0.64

``--codes`` random unit codes (256-d, the service's float codes' width) at random positions in a unit
square of latitude and longitude, stored, sealed and indexed (HNSW M 32, as the kind makes them) on a
Milvus standalone the run starts from the ``milvus`` wheel (or ``--milvus-uri``), then for each box side
``--queries`` codes searched for their top 10 inside the box ``(0, 0)-(side, side)`` both ways: the median
ms (one query at a time, at a timestamp taken after the fill, as the service reads) and the share of the
box's exact top 10 each finds (numpy's exact scores of every code in the box). The threshold in
``app/engine/index/kinds/milvus.py`` is chosen on these rows: exact where reading the codes stays within
tens of milliseconds. ``--ef 256,1024`` adds a column per value: the filtered HNSW at that ``ef``
(the kind's ``FILTERED_EF`` is chosen on them).
"""

from __future__ import annotations

import argparse
import contextlib
import time

import numpy as np

from bench.common import machine

DIM = 256
K = 10


def _floats(text: str) -> list[float]:
    return [float(t) for t in text.split(",")]


def measure(uri: str, n: int, sides: list[float], queries: int, seed: int = 0, efs: tuple[int, ...] = ()) -> list[dict]:
    """One row per box side: references in the box, and each way's median ms and recall of the exact top 10
    (Milvus's HNSW at the kind's ``ef`` for a filtered search, and at each of ``efs``)."""
    from app.engine.index.kinds.milvus import MAX_QUERY_ROWS, MilvusIndex

    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, DIM)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    at = rng.uniform(0.0, 1.0, (n, 2))  # lat, lon
    index = MilvusIndex(DIM, False, uri=uri, collection="bench_milvus_region")
    index.drop()  # a previous run's rows would count twice
    try:
        for lo in range(0, n, 4096):
            index.add(np.arange(lo, min(n, lo + 4096)), x[lo : lo + 4096], at[lo : lo + 4096])
        index.settle()
        index.read_after(index.fence())
        rows = []
        for side in sides:
            box = (0.0, 0.0, side, side)  # min_lon, min_lat, max_lon, max_lat
            inside = np.flatnonzero((at[:, 0] <= side) & (at[:, 1] <= side))
            row: dict = {"side": side, "in_box": len(inside)}
            if len(inside) > MAX_QUERY_ROWS:
                row["exact"] = None  # one query cannot read them all
            ways = [("exact", MAX_QUERY_ROWS, index.filtered_ef), ("milvus", 0, index.filtered_ef)]
            ways += [(f"ef{ef}", 0, ef) for ef in efs]
            for how, threshold, ef in ways:
                if how in row:
                    continue
                index.exact_filtered, index.filtered_ef = threshold, ef
                times, recalls = [], []
                for q in x[rng.choice(n, queries, replace=False)]:
                    best = inside[np.argsort(-(x[inside] @ q), kind="stable")[:K]]
                    t0 = time.perf_counter()
                    found = index.search(q[None], K, box=box)[1][0]
                    times.append((time.perf_counter() - t0) * 1000)
                    recalls.append(len(set(found.tolist()) & set(best.tolist())) / max(1, len(best)))
                row[how] = {"p50_ms": float(np.median(times)), "recall10": float(np.mean(recalls))}
            index.filtered_ef = ways[0][2]
            rows.append(row)
        return rows
    finally:
        index.drop()
        index.close()


def table(rows: list[dict]) -> str:
    efs = [k for k in rows[0] if k.startswith("ef")] if rows else []
    lines = [
        "| box side | references in the box | exact here: p50 ms | recall of the box's top 10 | "
        "Milvus's filtered HNSW: p50 ms | recall of the box's top 10 |"
        + "".join(f" HNSW ef {k[2:]}: p50 ms | recall |" for k in efs),
        "|---|---|---|---|---|---|" + "---|---|" * len(efs),
    ]
    for r in rows:
        ex, mv = r["exact"], r["milvus"]
        exact = f"{ex['p50_ms']:.1f} | {ex['recall10']:.3f}" if ex else "- | -"
        more = "".join(f" {r[k]['p50_ms']:.1f} | {r[k]['recall10']:.3f} |" for k in efs)
        lines.append(f"| {r['side']:g} | {r['in_box']:,} | {exact} | {mv['p50_ms']:.1f} | {mv['recall10']:.3f} |{more}")
    return "\n".join(lines)


@contextlib.contextmanager
def _server(uri: str | None):
    if uri is not None:
        yield uri
        return
    from tools.milvus_server import MilvusServer

    server = MilvusServer().start()
    try:
        yield server.uri
    finally:
        server.remove()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--codes", type=int, default=20_000)
    ap.add_argument("--sides", type=_floats, default=[0.05, 0.1, 0.2, 0.4, 0.64])
    ap.add_argument("--queries", type=int, default=15)
    ap.add_argument("--milvus-uri", default=None, help="a running Milvus server (else one from the wheel)")
    ap.add_argument("--ef", type=lambda t: tuple(int(x) for x in t.split(",")), default=(), help="more HNSW ef")
    args = ap.parse_args()
    print(machine(), flush=True)
    with _server(args.milvus_uri) as uri:
        rows = measure(uri, args.codes, args.sides, args.queries, efs=args.ef)
    print(table(rows))


if __name__ == "__main__":
    main()
