"""Index kinds for 10^5-10^7 references: search time, recall, memory and change costs.

    PYTHONPATH=$PWD nice -n 10 .venv/bin/python -m bench.index_scale --sizes 100000,1000000 [--write]

The collection: penn-campus-gps's real reference codes (ids 0..388, encoded once with the default pipeline
and cached in out/) plus synthetic codes drawn from a Gaussian fitted to them (bench/scale_codes.py), in one
float16 memory-mapped file that plays the store's copy of the codes. Queries: penn's real queries, and
synthetic queries made as noisy copies of synthetic references at the cosine real references of one place
have to each other (``--query-cosine``, by default the median cosine of a penn reference to its nearest
other penn reference).

What a user feels: the rank of each penn query's true match (a reference within 25 m of it) under the exact
search and under each compressed kind, and the exact search's own R@1/10/100 of the true match at each size,
without and with a region filter of 1 km (bench/true_match.py says how distractors get positions).

For every kind: one-thread search p50 (one query at a time, as the service searches), top-10 recall
against the exact search, penn queries' top-1 agreement with the exact search, train time, the cost of one
add and one remove at size, dump and load time, and the RAM the loaded index holds (resident growth of a
fresh process that loads it, so the hashtable and the allocator's overhead are counted, not only the file).
The float kind sweeps nprobe x shortlist and reports the cheapest setting meeting the targets.

``--milvus-up-to N`` adds the ``milvus`` kind at the sizes up to N, on a Milvus standalone started from the
``milvus`` wheel for the run (or ``--milvus-uri``): filled, sealed and indexed, then searched as the others.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import faiss
import numpy as np

from app.engine.index.ivf_lists import MAX_POINTS_PER_LIST, TWO_LEVEL_FROM, default_nlist
from app.engine.index.kinds.binary_ivf import BinaryIvfIndex
from app.engine.index.kinds.ivf_rabitq import IvfCompressedIndex
from bench.scale_codes import (
    CodeGenerator,
    PennCodes,
    chunks,
    codes_file,
    encode_penn,
    exact_search,
    fidelity,
    penn_positions,
    sign_bits,
)
from bench.true_match import (
    M_PER_DEG_LAT,
    Positions,
    TrueMatches,
    distractor_xy,
    exact_ranks,
    find_true_matches,
    found_ranks,
    kept,
    recall_at,
)

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "out" / "index_scale"
K = 10
#: The targets at 10^7 references.
TARGETS = {"p50_ms": 5.0, "recall10": 0.95, "penn_top1": 0.97, "ram_bytes_per_ref": 128, "change_ratio": 1.5}
#: The targets on the true match at 10^7: the share of exact's top-10 true matches an index keeps in its top
#: 10, and how far below exact's its R@10 of the true match may lie.
TRUE_TARGETS = {"kept10": 0.97, "r10_gap": 0.01}
#: The service's search settings for ivf-rabitq (``IvfCompressedIndex``'s defaults), marked in the sweep.
SERVICE_SEARCH = {"nprobe": 64, "shortlist": 100}
#: Threads for building (training, adding, the exact ground truth); searches are always timed on one. The
#: shared development machine allows two, and on a loaded one a single thread is faster (OpenMP barriers wait
#: on descheduled threads): GEOLOC_BENCH_BUILD_THREADS chooses, 1 by default.
KMEANS = ("two-level", "one-level")
BUILD_THREADS, SEARCH_THREADS = int(os.environ.get("GEOLOC_BENCH_BUILD_THREADS", "1")), 1


@dataclass
class KindFigures:
    n: int
    kind: str
    params: dict
    p50_ms: float
    recall10: float
    penn_top1: float | None
    train_s: float | None = None
    build_s: float | None = None
    add_ms: float | None = None
    remove_ms: float | None = None
    add_batch_ms: float | None = None  # per reference, added BATCH at a time (as the writer applies a run)
    dump_s: float | None = None
    file_bytes_per_ref: float | None = None
    load_s: float | None = None
    ram_bytes_per_ref: float | None = None
    load_peak_vs_file: float | None = None
    sweep: list[dict] = field(default_factory=list)
    true_r10: float | None = None
    true_kept10: float | None = None
    region_true_r10: float | None = None  # the true match's R@10 searched in its region's box (a kind that
    region_p50_ms: float | None = None  # filters by the positions it holds: milvus)


def _p50_ms(fn, queries: np.ndarray) -> tuple[float, list]:
    """Median ms of ``fn`` over single queries, and its results."""
    times, results = [], []
    for q in queries:
        t0 = time.perf_counter()
        results.append(fn(q[None]))
        times.append((time.perf_counter() - t0) * 1000)
    return float(np.median(times)), results


def _top1_details(found: np.ndarray, exact: np.ndarray, n_synth_q: int, n_penn: int) -> dict:
    """Top-1 figures that separate the meaningful neighbour from the crowd: synthetic queries' exact top-1
    is their source (cosine ~0.46, far above the ~0.25 of the best random code); penn queries whose exact
    top-1 is a real penn reference (not a synthetic distractor) are the ones where a real match is at stake."""
    on_penn = exact[n_synth_q:, 0] < n_penn
    agree = found[n_synth_q:, 0] == exact[n_synth_q:, 0]
    return {
        "synth_top1": float(np.mean(found[:n_synth_q, 0] == exact[:n_synth_q, 0])),
        "penn_top1_real_match": float(np.mean(agree[on_penn])) if on_penn.any() else float("nan"),
    }


@dataclass
class TrueContext:
    """The true matches at one size: which penn queries have one, and their ranks under the exact search."""

    truth: TrueMatches
    exact: np.ndarray  # ranks under the exact float search
    n_synth_q: int  # rows of the query matrix before penn's queries

    def figures(self, found: np.ndarray, exact: np.ndarray | None = None) -> dict:
        """R@10 of the true match in ``found`` (every query's top-10 ids) and the share of ``exact``'s top-10
        true matches it keeps (the float exact search unless another exact ranking is given)."""
        ranks = found_ranks(found[self.n_synth_q :], self.truth)
        return {
            "true_r10": recall_at(ranks, (10,))[10],
            "true_kept10": kept(ranks, self.exact if exact is None else exact),
        }


def _recall10(found: np.ndarray, exact: np.ndarray) -> float:
    return float(np.mean([len(set(f[f >= 0]) & set(e[e >= 0])) / K for f, e in zip(found, exact, strict=True)]))


#: References per add in the batched measure: a run of uploads the writer applies in one call
#: (``apply_changes``), whose list assignment is then one matrix product over the centroids.
BATCH = 100


def _change_costs(index, fresh: np.ndarray, first_id: int, singles: int | None = None) -> tuple[float, float, float]:
    """Median ms of adding one new reference, then of removing it again (the first ``singles`` codes, all by
    default), and ms per reference of adding them ``BATCH`` at a time (median over the batches), removed
    again (the collection ends as it began). A kind that holds positions is given each at (0, 0)."""
    adds, removes = [], []
    ids = np.arange(first_id, first_id + len(fresh), dtype=np.int64)
    one_by_one = ids[: len(ids) if singles is None else singles]
    at = (lambda m: (np.zeros((m, 2)),)) if index.holds_positions else (lambda m: ())
    for i in one_by_one:
        t0 = time.perf_counter()
        index.add(ids[i - first_id : i - first_id + 1], fresh[i - first_id][None], *at(1))
        adds.append((time.perf_counter() - t0) * 1000)
    for i in one_by_one:
        t0 = time.perf_counter()
        removed = index.remove([i])
        removes.append((time.perf_counter() - t0) * 1000)
        assert removed == 1, f"id {i} was not removed"
    batches = []
    for lo in range(0, len(fresh) - BATCH + 1, BATCH):
        t0 = time.perf_counter()
        index.add(ids[lo : lo + BATCH], fresh[lo : lo + BATCH], *at(BATCH))
        batches.append((time.perf_counter() - t0) * 1000 / BATCH)
    assert index.remove(ids[: len(batches) * BATCH]) == len(batches) * BATCH
    return float(np.median(adds)), float(np.median(removes)), float(np.median(batches))


_LOAD_PROBE = """
import json, resource, sys, time
import faiss
from app.engine.index.base import build_index
import app.engine.index.kinds.binary_ivf, app.engine.index.kinds.ivf_rabitq  # imports outside the measure
def rss():
    return int(open('/proc/self/statm').read().split()[1]) * 4096
before = rss(); peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
t0 = time.perf_counter()
binary = sys.argv[2] == 'binary'
# the float kind's re-rank codes are the bench's memory-mapped synthetic codes, not in its file: an external
# reader (never called here) loads the FAISS part alone
index = build_index(sys.argv[3], int(sys.argv[4]), binary, **({} if binary else {"float_codes": print}))
index.load(sys.argv[1])
seconds = time.perf_counter() - t0
after = rss(); peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
# the process's peak before the load (import transients) hides the load's own peak unless the load raised it
print(json.dumps({"seconds": seconds, "resident": after - before,
                  "peak": (peak if peak > peak_before else after) - before,
                  "ntotal": index.size}))
"""


def measure_load(path: Path, index) -> dict:
    """Load the dumped index through its kind in a fresh process: its time, the resident memory it adds and
    its peak."""
    binary = "binary" if index.binary else "float"
    root = str(Path(__file__).resolve().parents[1])
    out = subprocess.run(
        [sys.executable, "-c", _LOAD_PROBE, str(path), binary, index.kind, str(index.dim)],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": root},
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def _persist(index, n: int, path: Path) -> dict:
    t0 = time.perf_counter()
    index.dump(path)
    dump_s = time.perf_counter() - t0
    size = path.stat().st_size
    load = measure_load(path, index)
    path.unlink()
    return {
        "dump_s": dump_s,
        "file_bytes_per_ref": size / n,
        "load_s": load["seconds"],
        "ram_bytes_per_ref": load["resident"] / n,
        "load_peak_vs_file": load["peak"] / size,
    }


def _sample(codes: np.ndarray, n: int, m: int, rng: np.random.Generator) -> np.ndarray:
    rows = np.sort(rng.choice(n, min(m, n), replace=False))
    return np.asarray(codes[rows], dtype=np.float32)


def _set_kmeans(index, kmeans: str) -> None:
    """The service's training (two-level k-means from TWO_LEVEL_FROM lists), or one level at every size."""
    if kmeans not in KMEANS:
        raise ValueError(f"--kmeans takes {', '.join(KMEANS)}, not {kmeans!r}")
    if kmeans == "one-level":
        index.two_level_from = 1 << 62


def _kmeans_used(kmeans: str, nlist: int) -> str:
    return "two-level" if kmeans == "two-level" and nlist >= TWO_LEVEL_FROM else "one-level"


def build_float(
    codes, n: int, codec: str, kmeans: str, rng, progress, quantizer: str = "flat"
) -> tuple[IvfCompressedIndex, float, float]:
    """Train on a sample of the first ``n`` codes, then add them all in chunks; returns (index, train s, add s)."""
    index = IvfCompressedIndex(
        codes.shape[1],
        codec=codec,
        quantizer=quantizer,
        float_codes=lambda ids: np.asarray(codes[ids], dtype=np.float32),
    )
    _set_kmeans(index, kmeans)
    sample = _sample(codes, n, MAX_POINTS_PER_LIST * default_nlist(n), rng)
    t0 = time.perf_counter()
    index.nlist = default_nlist(n)
    index.train(sample)
    train_s = time.perf_counter() - t0
    del sample
    t0 = time.perf_counter()
    for lo, x in chunks(codes, n):
        index.add(np.arange(lo, lo + len(x), dtype=np.int64), x)
    build_s = time.perf_counter() - t0
    progress(
        f"  {codec} ({quantizer} quantizer): nlist {index.nlist}, {_kmeans_used(kmeans, index.nlist)} k-means,"
        f" trained in {train_s:.1f} s, {n:,} added in {build_s:.1f} s"
    )
    return index, train_s, build_s


def measure_float_kind(
    codes,
    n,
    codec,
    kmeans,
    queries,
    exact,
    n_synth_q,
    n_penn,
    sweep_nprobe,
    sweep_shortlist,
    gen,
    rng,
    progress,
    quantizer="flat",
    true: TrueContext | None = None,
):
    index, train_s, build_s = build_float(codes, n, codec, kmeans, rng, progress, quantizer)
    faiss.omp_set_num_threads(SEARCH_THREADS)
    sweep = []
    for nprobe in sweep_nprobe:
        for shortlist in sweep_shortlist:
            index.set_search(nprobe, shortlist)
            p50, res = _p50_ms(lambda q: index.search(q, K)[1][0], queries)
            found = np.stack(res)
            sweep.append(
                {
                    "nprobe": nprobe,
                    "shortlist": shortlist,
                    "p50_ms": p50,
                    "recall10": _recall10(found[:n_synth_q], exact[:n_synth_q]),
                    "penn_top1": float(np.mean(found[n_synth_q:, 0] == exact[n_synth_q:, 0])),
                    **_top1_details(found, exact, n_synth_q, n_penn),
                    **(true.figures(found) if true is not None else {}),
                }
            )
            progress(f"    nprobe {nprobe:4d} shortlist {shortlist:4d}: {sweep[-1]}")
    best = choose(sweep, None if true is None else recall_at(true.exact, (10,))[10])
    index.set_search(best["nprobe"], best["shortlist"])
    add_ms, remove_ms, add_batch_ms = _change_costs(index, gen.draw(5 * BATCH, rng), first_id=10**12)
    faiss.omp_set_num_threads(BUILD_THREADS)
    persist = _persist(index, n, OUT / f"float-{codec}-{kmeans}-{quantizer}-{n}.faiss")
    fig = KindFigures(
        n,
        f"ivf-{codec.lower()}" + ("" if quantizer == "flat" else f" ({quantizer} quantizer)"),
        {
            **{
                k: v
                for k, v in index.stats().items()
                if k in ("codec", "nlist", "nprobe", "shortlist", "code_bytes", "quantizer")
            },
            "kmeans": _kmeans_used(kmeans, index.nlist),
        },
        best["p50_ms"],
        best["recall10"],
        best["penn_top1"],
        train_s,
        build_s,
        add_ms,
        remove_ms,
        add_batch_ms,
        sweep=sweep,
        true_r10=best.get("true_r10"),
        true_kept10=best.get("true_kept10"),
        **persist,
    )
    index = None
    gc.collect()
    return fig


@contextlib.contextmanager
def _milvus_server(progress):
    """A Milvus standalone from the ``milvus`` wheel for this run (``tools/milvus_server.py``); its uri."""
    from tools.milvus_server import MilvusServer

    server = MilvusServer().start()
    progress(f"  Milvus standalone at {server.uri} (started in {server.started_in:.0f} s)")
    try:
        yield server.uri
    finally:
        server.remove()


def measure_milvus(
    codes, n, queries, exact, n_synth_q, gen, rng, progress, uri, true=None, place: Placement | None = None
) -> KindFigures:
    """The ``milvus`` kind (float codes, HNSW on the server at the kind's defaults) as the service configures
    it, filled with the first ``n`` codes at ``place``'s positions, sealed and indexed (``settle``), searched
    one query at a time at a timestamp taken after the fill (as the service reads); its RAM is the server's,
    not measured here. With ``true`` and ``place``, each penn query with a true match is searched again in the
    bounding box of its region (the filter the service sends Milvus): ``region_p50_ms`` and ``region_true_r10``."""
    from app.engine.index.kinds.milvus import MilvusIndex

    index = MilvusIndex(codes.shape[1], False, uri=uri, collection=f"bench_index_scale_{n}")
    index.drop()  # a previous run's rows would count twice
    t0 = time.perf_counter()
    for lo, x in chunks(codes, n):
        at = place.of(lo, len(x)) if place is not None else np.zeros((len(x), 2))
        index.add(np.arange(lo, lo + len(x), dtype=np.int64), np.asarray(x, np.float32), at)
    indexed = index.settle()
    build_s = time.perf_counter() - t0
    index.read_after(index.fence())
    progress(f"  milvus: {indexed:,} rows stored and indexed in {build_s:.1f} s")
    p50, res = _p50_ms(lambda q: index.search(q, K)[1][0], queries)
    found = np.stack(res)
    true_figures = true.figures(found) if true is not None else {}
    if true is not None and place is not None:
        true_figures |= place.region_figures(index, queries[n_synth_q:], true.truth)
        progress(
            f"  milvus in the region's box: {true_figures['region_true_r10']:.3f} R@10, "
            f"p50 {true_figures['region_p50_ms']:.2f} ms"
        )
    # a remove first reads which ids are stored, strongly consistent (a server time tick each): 50 are timed
    add_ms, remove_ms, add_batch_ms = _change_costs(index, gen.draw(3 * BATCH, rng), first_id=10**12, singles=50)
    index.drop()
    index.close()
    return KindFigures(
        n,
        "milvus",
        {"quantizer": "HNSW", "m": index.m, "ef_search": index.ef_search},
        p50,
        _recall10(found[:n_synth_q], exact[:n_synth_q]),
        float(np.mean(found[n_synth_q:, 0] == exact[n_synth_q:, 0])),
        build_s=build_s,
        add_ms=add_ms,
        remove_ms=remove_ms,
        add_batch_ms=add_batch_ms,
        true_r10=true_figures.get("true_r10"),
        true_kept10=true_figures.get("true_kept10"),
        region_true_r10=true_figures.get("region_true_r10"),
        region_p50_ms=true_figures.get("region_p50_ms"),
    )


@dataclass
class Placement:
    """Where the codes are (degrees), for a kind that stores positions: penn's references at their own,
    each synthetic code at its drawn one (``bench.true_match.distractor_xy``, the exact region ranks' draw)."""

    positions: Positions
    n_penn: int
    extent_m: float
    region_m: float
    seed: int

    def of(self, lo: int, count: int) -> np.ndarray:
        """(count, 2) lat, lon of the codes ``lo .. lo+count`` (one chunk)."""
        refs = self.positions.refs
        out = np.zeros((count, 2))
        penn = max(0, min(self.n_penn, lo + count) - lo)
        out[:penn] = refs[lo : lo + penn]
        if penn < count:
            xy = distractor_xy(lo, count, self.extent_m, self.seed)[penn:].astype(np.float64)
            lat0, lon0 = refs.mean(axis=0)
            out[penn:, 0] = lat0 + xy[:, 1] / M_PER_DEG_LAT
            out[penn:, 1] = lon0 + xy[:, 0] / (M_PER_DEG_LAT * np.cos(np.radians(lat0)))
        return out

    def region_figures(self, index, penn_queries: np.ndarray, truth: TrueMatches) -> dict:
        """Each true-match query searched in its region's bounding box: p50 ms and the true match's R@10."""
        from app.domain import Region

        found = np.full((truth.n_queries, K), -1, np.int64)
        times = []
        for row in truth.rows:
            lat, lon = self.positions.queries[row]
            box = Region(lat=float(lat), lon=float(lon), radius_m=self.region_m).bounding_box()
            t0 = time.perf_counter()
            ids = index.search(penn_queries[row][None], K, box=box)[1][0]
            times.append((time.perf_counter() - t0) * 1000)
            found[row] = ids
        return {
            "region_true_r10": recall_at(found_ranks(found, truth), (10,))[10],
            "region_p50_ms": float(np.median(times)),
        }


def meets_true_targets(s: dict, exact_r10: float) -> bool:
    """Whether a setting keeps the true match as the exact search does (TRUE_TARGETS)."""
    return (
        s.get("true_kept10") is not None
        and s["true_kept10"] >= TRUE_TARGETS["kept10"]
        and s["true_r10"] >= exact_r10 - TRUE_TARGETS["r10_gap"]
    )


def choose(sweep: list[dict], exact_r10: float | None = None) -> dict:
    """The fastest setting within the time target that keeps the true match as the exact search does (what
    users feel); else the fastest meeting the recall and penn targets; else, of those within the time
    target, the most accurate; else the fastest."""
    if exact_r10 is not None:
        true_ok = [s for s in sweep if s["p50_ms"] <= TARGETS["p50_ms"] and meets_true_targets(s, exact_r10)]
        if true_ok:
            return min(true_ok, key=lambda s: s["p50_ms"])
    ok = [s for s in sweep if s["recall10"] >= TARGETS["recall10"] and s["penn_top1"] >= TARGETS["penn_top1"]]
    if ok:
        return min(ok, key=lambda s: s["p50_ms"])
    fast = [s for s in sweep if s["p50_ms"] <= TARGETS["p50_ms"]]
    if fast:
        return max(fast, key=lambda s: (s["recall10"] + s["penn_top1"], -s["p50_ms"]))
    return min(sweep, key=lambda s: s["p50_ms"])


def measure_exact_float(codes, n, queries, progress, true: TrueContext | None = None) -> KindFigures | None:
    """The exhaustive float search (today's default) as the baseline row, while 4 bytes x 256 x n fits."""
    if n > 1_000_000:
        return None
    flat = faiss.IndexFlatIP(codes.shape[1])
    for _, x in chunks(codes, n):
        flat.add(x)
    faiss.omp_set_num_threads(SEARCH_THREADS)
    p50, _ = _p50_ms(lambda q: flat.search(q, K), queries[:50])
    faiss.omp_set_num_threads(BUILD_THREADS)
    progress(f"  exact float: p50 {p50:.2f} ms")
    flat = None
    return KindFigures(
        n,
        "flat (exact)",
        {},
        p50,
        1.0,
        1.0,
        ram_bytes_per_ref=4.0 * codes.shape[1] + 8,
        true_r10=None if true is None else recall_at(true.exact, (10,))[10],
        true_kept10=None if true is None else 1.0,
    )


def measure_binary(
    codes, n, queries, n_synth_q, sweep_nprobe, kmeans, gen, rng, progress, true: TrueContext | None = None
) -> list[KindFigures]:
    """Binary IVF against the exhaustive Hamming search, on the sign bits of the same codes. Agreement
    counts ties as agreeing (Hamming distances tie often): top-1 agrees when its distance equals the exact
    top-1's, and a top-10 hit is any result at most the exact 10th distance away."""
    bits = codes.shape[1]
    flat = faiss.IndexBinaryFlat(bits)
    for _, x in chunks(codes, n):
        flat.add(sign_bits(x))
    qb = sign_bits(queries)
    ed, ei = flat.search(qb, K)
    hamming_ranks = None if true is None else found_ranks(ei[n_synth_q:], true.truth)
    faiss.omp_set_num_threads(SEARCH_THREADS)
    flat_p50, _ = _p50_ms(lambda q: flat.search(q, K), qb[:100])
    faiss.omp_set_num_threads(BUILD_THREADS)
    nlist = default_nlist(n)
    sample = sign_bits(_sample(codes, n, 64 * nlist, rng))
    index = BinaryIvfIndex(bits, nlist=nlist)
    _set_kmeans(index, kmeans)
    t0 = time.perf_counter()
    index.train(sample)
    train_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for lo, x in chunks(codes, n):
        index.add(np.arange(lo, lo + len(x), dtype=np.int64), sign_bits(x))
    build_s = time.perf_counter() - t0
    faiss.omp_set_num_threads(SEARCH_THREADS)
    sweep = []
    for nprobe in sweep_nprobe:
        index.nprobe = nprobe
        p50, res = _p50_ms(lambda q: index.search(q, K), qb)
        d = np.rint((1.0 - np.concatenate([r[0] for r in res])) * bits)  # scores back to Hamming distances
        d[np.concatenate([r[1] for r in res]) < 0] = bits + 1
        top1 = float(np.mean(d[:, 0] == ed[:, 0]))
        hits = float(np.mean((d <= ed[:, -1:]).sum(axis=1).clip(max=K) / K))
        ids = np.stack([r[1][0] for r in res])
        truth = {} if true is None else true.figures(ids, hamming_ranks)
        sweep.append({"nprobe": nprobe, "p50_ms": p50, "top1": top1, "recall10": hits, **truth})
        progress(f"    binary nprobe {nprobe:4d}: {sweep[-1]}")
    best = min((s for s in sweep if s["top1"] >= 0.97), key=lambda s: s["p50_ms"], default=sweep[-1])
    index.nprobe = best["nprobe"]
    add_ms, remove_ms, add_batch_ms = _change_costs(index, sign_bits(gen.draw(5 * BATCH, rng)), first_id=10**12)
    faiss.omp_set_num_threads(BUILD_THREADS)
    persist = _persist(index, n, OUT / f"binary-{n}.faiss")
    exact = KindFigures(
        n,
        "binary flat (exact Hamming)",
        {},
        flat_p50,
        1.0,
        1.0,
        ram_bytes_per_ref=bits / 8 + 8,
        true_r10=None if true is None else recall_at(hamming_ranks, (10,))[10],
        true_kept10=None if true is None else 1.0,
    )
    fig = KindFigures(
        n,
        "binary-ivf",
        {"nlist": index.nlist, "nprobe": index.nprobe, "code_bytes": bits // 8, "kmeans": _kmeans_used(kmeans, nlist)},
        best["p50_ms"],
        best["recall10"],
        best["top1"],
        train_s,
        build_s,
        add_ms,
        remove_ms,
        add_batch_ms,
        sweep=sweep,
        true_r10=best.get("true_r10"),
        true_kept10=best.get("true_kept10"),
        **persist,
    )
    flat = index = None
    gc.collect()
    return [exact, fig]


def load_penn(path: Path, manifest: Path, models: Path, config: str, progress) -> PennCodes:
    if path.exists():
        return PennCodes.load(path)
    progress(f"encoding penn-campus-gps with {config} (once; cached in {path})")
    penn = encode_penn(manifest, models, config)
    path.parent.mkdir(parents=True, exist_ok=True)
    penn.save(path)
    return penn


def _save(figures: list[KindFigures], context: dict, out: Path) -> None:
    """Figures so far (a run cut short keeps what it measured)."""
    (out / "figures.json").write_text(json.dumps({"context": context, "figures": [asdict(f) for f in figures]}))


def run(args, progress=print) -> tuple[list[KindFigures], dict]:
    global OUT
    OUT = args.out
    args.out.mkdir(parents=True, exist_ok=True)
    faiss.omp_set_num_threads(BUILD_THREADS)
    penn = load_penn(args.penn_codes, args.manifest, args.models_dir, args.config, progress)
    gen = CodeGenerator.fit(penn.refs)
    nn = penn.refs @ penn.refs.T
    np.fill_diagonal(nn, -1)
    cosine = args.query_cosine or float(np.median(nn.max(axis=1)))
    sizes = sorted(args.sizes)
    t0 = time.perf_counter()
    codes = codes_file(args.out, max(sizes), penn, gen, args.seed)
    progress(f"codes: {codes.shape[0]:,} x {codes.shape[1]} float16 in {args.out} ({time.perf_counter() - t0:.0f} s)")
    rng = np.random.default_rng([args.seed, 7])
    n_penn = len(penn.refs)
    src = rng.choice(np.arange(n_penn, sizes[0]), args.queries, replace=False)
    synth_q = gen.noisy_copies(np.asarray(codes[np.sort(src)], np.float32), cosine, rng)
    queries = np.ascontiguousarray(np.vstack([synth_q, penn.queries]), dtype=np.float32)
    n_synth_q = len(synth_q)
    figures: list[KindFigures] = []
    context = {"query_cosine": cosine, "n_penn_refs": n_penn, "n_penn_queries": len(penn.queries)}
    context["fidelity"] = fidelity(penn, gen, np.random.default_rng([args.seed, 11]))
    progress(f"generator against penn's real codes: {context['fidelity']}")
    positions = Positions(*penn_positions(args.manifest))
    if (len(positions.refs), len(positions.queries)) != (n_penn, len(penn.queries)):
        raise SystemExit(f"{args.manifest} does not list the cached penn codes ({args.penn_codes}): encode them again")
    truth = find_true_matches(positions, args.radius_m, args.region_m)
    context["true_match"] = {
        "radius_m": args.radius_m,
        "region_m": args.region_m,
        "extent_km": args.extent_km,
        "queries": truth.count,
        "penn_queries": truth.n_queries,
        "sizes": {},
    }
    milvus_uri = args.milvus_uri
    with contextlib.ExitStack() as servers:  # a Milvus server this run starts is removed when it ends
        for n in sizes:
            progress(f"{n:,} references")
            t0 = time.perf_counter()
            _, exact = exact_search(codes, n, queries, K)
            context[f"exact_penn_top1_is_penn_{n}"] = float(np.mean(exact[n_synth_q:, 0] < n_penn))
            progress(f"  exact top-{K} in {time.perf_counter() - t0:.0f} s")
            t0 = time.perf_counter()
            ranks = exact_ranks(codes, n, penn.queries, truth, n_penn, args.extent_km * 1000, args.region_m, args.seed)
            true = TrueContext(truth, ranks.ranks, n_synth_q)
            context["true_match"]["sizes"][str(n)] = {
                "exact": recall_at(ranks.ranks),
                "region": recall_at(ranks.region_ranks),
                "region_distractors": ranks.region_distractors,
                "exact_median_rank": float(np.median(ranks.ranks)),
            }
            progress(f"  true match: {context['true_match']['sizes'][str(n)]} ({time.perf_counter() - t0:.0f} s)")
            base = measure_exact_float(codes, n, queries, progress, true)
            if base is not None:
                figures.append(base)
            for kmeans in args.kmeans:
                for codec in args.codecs:
                    for quantizer in args.quantizer:
                        figures.append(
                            measure_float_kind(
                                codes,
                                n,
                                codec,
                                kmeans,
                                queries,
                                exact,
                                n_synth_q,
                                n_penn,
                                args.nprobe,
                                args.shortlist,
                                gen,
                                rng,
                                progress,
                                quantizer,
                                true,
                            )
                        )
                        _save(figures, context, args.out)
            if n <= args.milvus_up_to:
                uri = milvus_uri or (milvus_uri := servers.enter_context(_milvus_server(progress)))
                place = Placement(positions, n_penn, args.extent_km * 1000, args.region_m, args.seed)
                figures.append(
                    measure_milvus(codes, n, queries, exact, n_synth_q, gen, rng, progress, uri, true, place)
                )
                _save(figures, context, args.out)
            if not args.no_binary:
                exact_hamming = None
                for kmeans in args.kmeans:
                    rows = measure_binary(codes, n, queries, n_synth_q, args.nprobe, kmeans, gen, rng, progress, true)
                    figures += rows if exact_hamming is None else rows[1:]
                    exact_hamming = rows[0]
                    _save(figures, context, args.out)
    return figures, context


def _quantizers(text: str) -> list[str]:
    """--quantizer's values, checked before any index is built."""
    names = text.split(",")
    if not set(names) <= {"flat", "hnsw"}:
        raise argparse.ArgumentTypeError(f"flat and/or hnsw, not {text!r}")
    return names


def _fmt(v, spec: str) -> str:
    return "" if v is None else format(v, spec)


def table(figures: list[KindFigures]) -> str:
    """One row per size and kind at its chosen setting (every measured figure is in figures.json)."""
    base = {f.kind: f for f in figures if f.n == min(x.n for x in figures)}
    head = (
        "| references | kind | nlist / nprobe / shortlist | p50 ms | true match R@10 | exact's top-10 true matches "
        f"kept | top-10 recall | RAM B/ref | add ms | add ms per reference, {BATCH} at a time | remove ms | "
        "add / batched / remove vs smallest | train s | build s | load s |\n|" + "---|" * 15
    )
    rows = []
    for f in figures:
        b = base.get(f.kind)
        ratio = (
            f"{f.add_ms / b.add_ms:.1f}x / {f.add_batch_ms / b.add_batch_ms:.1f}x / {f.remove_ms / b.remove_ms:.1f}x"
            if b is not None and f.add_ms and b.add_ms and f.add_batch_ms and b.add_batch_ms
            else ""
        )
        search = " / ".join(str(f.params[k]) for k in ("nlist", "nprobe", "shortlist") if k in f.params)
        if "ef_search" in f.params:  # milvus: its HNSW's degree and search depth
            search = f"HNSW M {f.params['m']} / ef {f.params['ef_search']}"
        rows.append(
            f"| {f.n:,} | {f.kind} | {search} | {f.p50_ms:.2f} | {_fmt(f.true_r10, '.3f')} | "
            f"{_fmt(f.true_kept10, '.0%')} | {f.recall10:.3f} | {_fmt(f.ram_bytes_per_ref, '.0f')} | "
            f"{_fmt(f.add_ms, '.3f')} | {_fmt(f.add_batch_ms, '.3f')} | {_fmt(f.remove_ms, '.3f')} | {ratio} | "
            f"{_fmt(f.train_s, '.0f')} | {_fmt(f.build_s, '.0f')} | {_fmt(f.load_s, '.2f')} |"
        )
    return "\n".join([head, *rows])


def sweep_table(figures: list[KindFigures]) -> str:
    """The float kinds' sweep at the largest size (every size's is in figures.json); the service's own
    setting marked."""
    largest = max(f.n for f in figures)
    lines = [
        "| references | kind | nprobe | shortlist | p50 ms | true match R@10 | exact's top-10 true matches kept | "
        "top-10 recall |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f in figures:
        if "shortlist" not in f.params or f.n != largest:
            continue
        for s in f.sweep:
            service = f.kind == "ivf-rabitq" and all(s.get(k) == v for k, v in SERVICE_SEARCH.items())
            lines.append(
                f"| {f.n:,} | {f.kind} | {s['nprobe']}{' (service)' if service else ''} | {s['shortlist']} | "
                f"{s['p50_ms']:.2f} | {_fmt(s.get('true_r10'), '.3f')} | {_fmt(s.get('true_kept10'), '.0%')} | "
                f"{s['recall10']:.3f} |"
            )
    return "\n".join(lines)


def true_match_table(t: dict, figures: list[KindFigures] = ()) -> str:
    """The exact search's R@k of the true match at each size, without and with the region filter; where
    milvus was measured, its R@10 and p50 searched in the region's bounding box (the positions it holds)."""
    boxed = {f.n: f for f in figures if f.region_true_r10 is not None}
    extra = " milvus in the region's box: R@10 / p50 ms |" if boxed else ""
    lines = [
        f"| references | exact R@1 / 10 / 100 | median rank | distractors within {t['region_m']:.0f} m (median) | "
        f"with the {t['region_m']:.0f} m filter: R@1 / 10 / 100 |{extra}",
        "|---|---|---|---|---|" + ("---|" if boxed else ""),
    ]
    r = lambda d: " / ".join(f"{d[k]:.3f}" for k in sorted(d, key=int))  # noqa: E731
    for n, f in sorted(t["sizes"].items(), key=lambda kv: int(kv[0])):
        m = boxed.get(int(n))
        cell = (f" {m.region_true_r10:.3f} / {m.region_p50_ms:.2f} |" if m else " |") if boxed else ""
        lines.append(
            f"| {int(n):,} | {r(f['exact'])} | {f['exact_median_rank']:,.0f} | {f['region_distractors']:,.0f} | "
            f"{r(f['region'])} |{cell}"
        )
    return "\n".join(lines)


def fidelity_line(f: dict) -> str:
    """The generator against penn's real codes, in words (``scale_codes.fidelity``)."""
    pct = lambda d: " / ".join(f"{v:.3f}" for v in d.values())  # noqa: E731
    return (
        "The generator against penn's real codes (cosine percentiles 50 / 90 / 99 / 99.9 of query-reference pairs): "
        f"real references {pct(f['query_real_cos_pct'])}, synthetic {pct(f['query_synthetic_cos_pct'])}; a query's "
        f"best real reference {f['best_real_median']:.3f} (median), the best of as many synthetic codes "
        f"{f['best_synthetic_same_count_median']:.3f}; effective dimension (participation ratio) "
        f"{f['effective_dim_real']:.0f} real, {f['effective_dim_synthetic']:.0f} synthetic, of 256; real views of "
        f"one place (99.9th percentile of reference pairs) {f['real_ref_pairs_cos_999']:.3f}."
    )


def true_match_section(t: dict, figures: list[KindFigures] = ()) -> str:
    """The true match's curve in words and a table."""
    return (
        f"**The true match** (a penn reference within {t['radius_m']:.0f} m of the query; {t['queries']} of the "
        f"{t['penn_queries']} penn queries have one): its rank under the exact search, how the descriptor's power "
        f"fades as distractors grow, and the same with a region filter of {t['region_m']:.0f} m around the query "
        "(what a coarse prior gives back; distractors placed uniformly over a square "
        f"{t['extent_km']:.0f} km wide around the campus, penn's references at their own positions):\n\n"
        f"{true_match_table(t, figures)}"
    )


def section(figures: list[KindFigures], context: dict) -> str:
    command, when = context["command"], context["finished"]
    penn = ", ".join(f"{k.rsplit('_', 1)[1]}: {v:.0%}" for k, v in context.items() if k.startswith("exact_penn"))
    return (
        f"## Index kinds at 10^5-10^7 references\n\n`{command}` ({when}; synthetic codes fitted to "
        f"penn's real codes, {context['n_penn_refs']} real penn references included, {context['n_penn_queries']} "
        f"real penn queries; synthetic queries at cosine {context['query_cosine']:.2f} to their source; "
        "medians; one FAISS thread for searches, two for building):\n\n"
        f"{table(figures)}\n\nHow often a penn query's exact top-1 is still a penn reference: {penn}.\n\n"
        f"{true_match_section(context['true_match'], figures)}\n\n"
        f"{fidelity_line(context['fidelity'])}\n\n"
        "Sweep at the largest size (the row above is the fastest setting within 5 ms that keeps at least 97 % "
        "of the exact search's top-10 true matches with its R@10 of the true match within 0.01 of exact's; else "
        "the fastest meeting "
        "recall >= 0.95 and top-1 >= 97 %; else the most accurate within 5 ms):"
        f"\n\n{sweep_table(figures)}\n"
    )


def _ints(text: str) -> list[int]:
    return [int(float(t)) for t in text.split(",") if t]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=_ints, default=[100_000, 1_000_000])
    ap.add_argument("--codecs", type=lambda t: t.split(","), default=["PQ32", "RaBitQ"])
    ap.add_argument("--nprobe", type=_ints, default=[16, 32, 64, 128])
    ap.add_argument("--shortlist", type=_ints, default=[50, 100, 200])
    ap.add_argument("--queries", type=int, default=200, help="synthetic queries (penn's real ones are added)")
    ap.add_argument("--query-cosine", type=float, default=None)
    ap.add_argument("--no-binary", action="store_true")
    ap.add_argument(
        "--kmeans",
        type=lambda t: t.split(","),
        default=["two-level"],
        help="coarse training: two-level (the service's, from TWO_LEVEL_FROM lists) and/or one-level",
    )
    ap.add_argument(
        "--quantizer",
        type=_quantizers,
        default=["flat"],
        help="ivf-rabitq's coarse quantizer: flat (the service's, exact) and/or hnsw (an HNSW graph)",
    )
    ap.add_argument("--radius-m", type=float, default=25.0, help="a true match lies this near the query")
    ap.add_argument("--region-m", type=float, default=1000.0, help="the region filter's radius")
    ap.add_argument(
        "--extent-km", type=float, default=100.0, help="distractors' positions: uniform over a square this wide"
    )
    ap.add_argument(
        "--milvus-up-to",
        type=int,
        default=0,
        help="measure the milvus kind at the sizes up to this (on a server from the milvus wheel, or --milvus-uri)",
    )
    ap.add_argument("--milvus-uri", default=None, help="a running Milvus server to measure on instead")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--penn-codes", type=Path, default=REPO / "out" / "penn_codes.npz")
    ap.add_argument("--manifest", type=Path, default=REPO / "data" / "manifests" / "penn-campus-gps.csv")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--config", default="lite2-hybrid-384")
    ap.add_argument("--write", action="store_true", help="write the section into docs/benchmarks.md")
    ap.add_argument(
        "--render", type=Path, help="measure nothing: render the section from a run's figures.json (its command)"
    )
    args = ap.parse_args()
    if args.render is not None:
        saved = json.loads(args.render.read_text())
        figures, context = [KindFigures(**f) for f in saved["figures"]], saved["context"]
    else:
        figures, context = run(args, progress=lambda m: print(m, flush=True))
        context["command"] = "PYTHONPATH=$PWD .venv/bin/python -m bench.index_scale " + " ".join(sys.argv[1:])
        context["finished"] = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
        _save(figures, context, args.out)
    text = section(figures, context)
    print(text)
    if args.write:
        from bench.common import write_section

        write_section("index-scale", text)


if __name__ == "__main__":
    main()
