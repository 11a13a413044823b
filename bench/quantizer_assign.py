"""What one add to ``ivf-rabitq`` costs, by the number of lists and the number of codes stored: with its
exact coarse quantizer (one at a time and ``--batch`` at a time), with an HNSW graph over the centroids, and
with a scan of 8-bit centroids whose best ``--refine`` are re-scored exactly.

    .venv/bin/python -m bench.quantizer_assign --nlists 1024,4096,16384 --fills 10000 --ef 64,256 --refine 8

Why: an add to an IVF first assigns the new code to its nearest list, then encodes it and appends it to
that list. ``default_nlist`` grows the lists as 4 sqrt(n) (1,024 at 10^5, 16,384 at 10^7), so the target
"add per change at 10^7 <= 1.5x its cost at 10^5" turns on how the assignment's cost grows with ``nlist``,
and on nothing else that grows with the collection. The exact scan reads every centroid once per add
(``nlist`` x 256 floats: 16 MB at 16,384 lists, memory-bound) or, for a batch, multiplies the batch by them
(compute-bound: ``nlist`` x 256 multiply-adds per code either way); a cheaper assignment must skip
centroids, and the rows say how often it then misses the nearest one.

For each ``nlist``: random unit centroids (the bench's synthetic codes are nearly isotropic: about 210
effective dimensions of 256, ``bench.index_scale``'s fidelity figures; trained centroids of such codes are
spread like them), the kind's FAISS index (``IVF{nlist},RaBitQ``; inner product, hashtable direct map)
with each quantizer, filled with ``--fills`` codes, then the median of ``--adds`` single adds (then removed
again), the median per code of adding them ``--batch`` at a time, and how often the list a code went to is
its exact nearest centroid. One thread.
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


def _quantizer(how: str, centroids: np.ndarray) -> faiss.Index:
    """The coarse quantizer named ``how`` over ``centroids``: "exact", "hnsw" (efSearch set per row) or
    "sq8-refine K" (an 8-bit scan whose best K are re-scored exactly, FAISS's ``IndexRefine``)."""
    if how == "exact":
        q = faiss.IndexFlatIP(DIM)
    elif how == "hnsw":
        q = faiss.IndexHNSWFlat(DIM, 32, faiss.METRIC_INNER_PRODUCT)
    else:
        q = faiss.index_factory(DIM, "SQ8,Refine(Flat)", faiss.METRIC_INNER_PRODUCT)  # an IndexRefine
        q.k_factor = int(how.split()[1])
        q.train(centroids)
    q.add(centroids)
    return q


def one_nlist(
    nlist: int, fills: list[int], hows: list[str], efs: list[int], adds: int, batch: int, rng: np.random.Generator
) -> list[dict]:
    """Rows of (fill, quantizer): add ms (median), add ms per code ``batch`` at a time (exact rows only),
    assignment = exact nearest centroid (share). ``hows``: "exact", "hnsw" (one row per ``efs``),
    "sq8-refine K"."""
    centroids = unit_rows(rng.standard_normal((nlist, DIM), dtype=np.float32))
    train = unit_rows(rng.standard_normal((20_000, DIM), dtype=np.float32))
    fill_codes = unit_rows(rng.standard_normal((max(fills), DIM), dtype=np.float32))
    new = unit_rows(rng.standard_normal((adds, DIM), dtype=np.float32))
    exact = faiss.IndexFlatIP(DIM)
    exact.add(centroids)
    _, nearest = exact.search(new, 1)
    new_ids = np.arange(10**12, 10**12 + adds, dtype=np.int64)
    rows = []
    for how in hows:
        quantizer = _quantizer(how, centroids)
        index = faiss.IndexIVFRaBitQ(quantizer, DIM, nlist, faiss.METRIC_INNER_PRODUCT)
        index.train(train)  # the quantizer already holds the centroids: this trains the codec
        index.set_direct_map_type(faiss.DirectMap.Hashtable)
        stored = 0
        for fill in sorted(fills):
            index.add_with_ids(fill_codes[stored:fill], np.arange(stored, fill))
            stored = fill
            for ef in efs if how == "hnsw" else [None]:
                if ef is not None:
                    quantizer.hnsw.efSearch = ef
                rows.append(_row(index, quantizer, how, ef, new, new_ids, nearest, batch, nlist, fill))
    return rows


def _row(index, quantizer, how, ef, new, new_ids, nearest, batch, nlist, fill) -> dict:
    single = []
    for i in range(len(new)):
        t = time.perf_counter()
        index.add_with_ids(new[i : i + 1], new_ids[i : i + 1])
        single.append((time.perf_counter() - t) * 1e3)
    index.remove_ids(faiss.IDSelectorArray(new_ids))
    batched = []
    if how == "exact":
        for lo in range(0, len(new) - batch + 1, batch):
            t = time.perf_counter()
            index.add_with_ids(new[lo : lo + batch], new_ids[lo : lo + batch])
            batched.append((time.perf_counter() - t) * 1e3 / batch)
        index.remove_ids(faiss.IDSelectorArray(new_ids))
    _, assigned = quantizer.search(new, 1)
    name = f"hnsw efSearch {ef}" if how == "hnsw" else how
    row = {
        "nlist": nlist,
        "fill": fill,
        "how": name,
        "add_ms": statistics.median(single),
        "batch_ms": statistics.median(batched) if batched else None,
        "agree": float(np.mean(assigned[:, 0] == nearest[:, 0])),
    }
    each = f", {row['batch_ms']:.3f} ms each {batch} at a time" if batched else ""
    print(f"nlist {nlist:,} stored {fill:,} {name}: add {row['add_ms']:.3f} ms{each}, "
          f"list = exact nearest {row['agree']:.3f}", flush=True)  # fmt: skip
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nlists", type=_ints, default=[1024, 4096, 16384])
    ap.add_argument("--fills", type=_ints, default=[10_000])
    ap.add_argument("--ef", type=_ints, default=[64, 256])
    ap.add_argument("--refine", type=_ints, default=[8], help="exact re-scores after the 8-bit scan")
    ap.add_argument("--adds", type=int, default=1000)
    ap.add_argument("--batch", type=int, default=100)
    args = ap.parse_args()
    faiss.omp_set_num_threads(1)
    print(machine(), flush=True)
    rng = np.random.default_rng(0)
    hows = ["exact", "hnsw", *(f"sq8-refine {k}" for k in args.refine)]
    rows = [r for nlist in args.nlists for r in one_nlist(nlist, args.fills, hows, args.ef, args.adds, args.batch, rng)]
    # every row against the exact quantizer at the fewest lists: the cost the target compares with
    base = {r["fill"]: r for r in rows if r["nlist"] == args.nlists[0] and r["how"] == "exact"}
    first = f"{args.nlists[0]:,}"
    print()
    batched, vs = f"ms per add, {args.batch} at a time", f"vs exact, {first} lists"
    print(f"| lists | codes stored | quantizer | add ms (median) | {vs} | {batched} | {vs} | list = exact nearest |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        b = base[r["fill"]]
        batch = "" if r["batch_ms"] is None else f"{r['batch_ms']:.3f}"
        batch_ratio = "" if r["batch_ms"] is None else f"{r['batch_ms'] / b['batch_ms']:.1f}x"
        print(f"| {r['nlist']:,} | {r['fill']:,} | {r['how']} | {r['add_ms']:.3f} | {r['add_ms'] / b['add_ms']:.1f}x | "
              f"{batch} | {batch_ratio} | {r['agree']:.3f} |")  # fmt: skip


if __name__ == "__main__":
    main()
