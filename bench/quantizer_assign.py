"""What one add to ``ivf-rabitq`` costs, by the number of lists and the number of codes stored, with its
exact coarse quantizer and with an HNSW graph over the centroids.

    .venv/bin/python -m bench.quantizer_assign --nlists 1024,4096,16384 --fills 10000,200000 --ef 32,64,256

Why: an add to an IVF first assigns the new code to its nearest list (a flat scan of the ``nlist``
centroids, or a search of an HNSW graph over them), then encodes it and appends it to that list.
``default_nlist`` grows the lists as 4 sqrt(n) (1,024 at 10^5, 16,384 at 10^7), so the target "add per
change at 10^7 <= 1.5x its cost at 10^5" turns on how the assignment's cost grows with ``nlist``, and on
nothing else that grows with the collection.

For each ``nlist``: random unit centroids (the bench's synthetic codes are nearly isotropic: about 210
effective dimensions of 256, ``bench.index_scale``'s fidelity figures; trained centroids of such codes are
spread like them), the kind's FAISS index (``IVF{nlist},RaBitQ``, the service's exact quantizer, then
``IVF{nlist}_HNSW32,RaBitQ`` at each ``--ef``; inner product, hashtable direct map) filled with ``--fills``
codes, then the median of ``--adds`` single adds (then removed again), and how often the list a code went
to is its exact nearest centroid. One thread.
"""

from __future__ import annotations

import argparse
import statistics
import time

import faiss
import numpy as np

from bench.common import machine
from bench.scale_codes import unit_rows

DIM = 256


def _ints(text: str) -> list[int]:
    return [int(t) for t in text.split(",")]


def one_nlist(nlist: int, fills: list[int], efs: list[int | None], adds: int, rng: np.random.Generator) -> list[dict]:
    """Rows of (fill, ef): add ms (median), assignment = exact nearest centroid (share); ``efs`` None: the
    exact quantizer."""
    graph_kind = efs != [None]
    lists = f"IVF{nlist}_HNSW32" if graph_kind else f"IVF{nlist}"
    index = faiss.index_factory(DIM, f"{lists},RaBitQ", faiss.METRIC_INNER_PRODUCT)
    ivf = faiss.extract_index_ivf(index)
    centroids = unit_rows(rng.standard_normal((nlist, DIM), dtype=np.float32))
    ivf.quantizer.add(centroids)
    index.train(unit_rows(rng.standard_normal((20_000, DIM), dtype=np.float32)))
    index.set_direct_map_type(faiss.DirectMap.Hashtable)
    graph = faiss.downcast_index(ivf.quantizer) if graph_kind else None
    exact = faiss.IndexFlatIP(DIM)
    exact.add(centroids)
    new = unit_rows(rng.standard_normal((adds, DIM), dtype=np.float32))
    _, nearest = exact.search(new, 1)
    new_ids = np.arange(10**12, 10**12 + adds, dtype=np.int64)
    rows, stored = [], 0
    for fill in sorted(fills):
        if graph is not None:
            graph.hnsw.efSearch = 64
        for lo in range(stored, fill, 50_000):
            n = min(50_000, fill - lo)
            index.add_with_ids(unit_rows(rng.standard_normal((n, DIM), dtype=np.float32)), np.arange(lo, lo + n))
        stored = fill
        for ef in efs:
            if graph is not None:
                graph.hnsw.efSearch = ef
            ms = []
            for i in range(adds):
                t = time.perf_counter()
                index.add_with_ids(new[i : i + 1], new_ids[i : i + 1])
                ms.append((time.perf_counter() - t) * 1e3)
            index.remove_ids(faiss.IDSelectorArray(new_ids))
            _, assigned = ivf.quantizer.search(new, 1)
            agree = float(np.mean(assigned[:, 0] == nearest[:, 0]))
            how = "exact" if ef is None else f"hnsw efSearch {ef}"
            rows.append({"nlist": nlist, "fill": fill, "how": how, "add_ms": statistics.median(ms), "agree": agree})
            print(f"nlist {nlist:,} stored {fill:,} {how}: add {rows[-1]['add_ms']:.3f} ms, "
                  f"list = exact nearest {agree:.3f}", flush=True)  # fmt: skip
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nlists", type=_ints, default=[1024, 4096, 16384])
    ap.add_argument("--fills", type=_ints, default=[10_000, 200_000])
    ap.add_argument("--ef", type=_ints, default=[16, 32, 64, 256])
    ap.add_argument("--adds", type=int, default=1000)
    args = ap.parse_args()
    faiss.omp_set_num_threads(1)
    print(machine(), flush=True)
    rng = np.random.default_rng(0)
    rows = []
    for nlist in args.nlists:
        rows += one_nlist(nlist, args.fills, [None], args.adds, rng)
        rows += one_nlist(nlist, args.fills, args.ef, args.adds, rng)
    base = {(r["fill"], r["how"]): r["add_ms"] for r in rows if r["nlist"] == args.nlists[0]}
    print()
    first = f"{args.nlists[0]:,}"
    print(f"| lists | codes stored | quantizer | add ms (median) | vs {first} lists | list = exact nearest |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        ratio = r["add_ms"] / base[(r["fill"], r["how"])]
        print(f"| {r['nlist']:,} | {r['fill']:,} | {r['how']} | {r['add_ms']:.3f} | {ratio:.2f}x | {r['agree']:.3f} |")


if __name__ == "__main__":
    main()
