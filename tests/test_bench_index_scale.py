"""The index-scale benchmark runs end to end at a tiny size and reports figures that mean what they say."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.scale_codes import CodeGenerator, PennCodes, codes_file, effective_dimension, exact_search, penn_positions
from bench.true_match import Positions, distractor_xy, exact_ranks, find_true_matches, found_ranks, kept, recall_at

REPO = Path(__file__).resolve().parents[1]


#: Scores this close count as a tie (float32 dot products of unit vectors summed in another order).
TIE = 4e-6


def fake_penn(path: Path) -> Path:
    """Stand-in for the cached real codes (a fresh clone has no fitted pipeline): clustered unit codes, five
    references per place 100 m apart, the queries of the first 20 places at their place; returns the manifest
    that gives their positions."""
    rng = np.random.default_rng(0)
    centres = rng.standard_normal((40, 256)).astype(np.float32)
    refs = centres[np.repeat(np.arange(40), 5)] + rng.standard_normal((200, 256)).astype(np.float32)
    queries = centres[:20] + rng.standard_normal((20, 256)).astype(np.float32)
    PennCodes(
        refs / np.linalg.norm(refs, axis=1, keepdims=True), queries / np.linalg.norm(queries, axis=1, keepdims=True)
    ).save(path)
    place = lambda i: (39.95 + (i % 8) * 0.0009, -75.19 + (i // 8) * 0.0012)  # noqa: E731
    lines = ["image,lat,lon,split,group"]
    lines += [f"r{i}.jpg,{place(i // 5)[0]},{place(i // 5)[1]},db,r{i}" for i in range(200)]
    lines += [f"q{i}.jpg,{place(i)[0]},{place(i)[1]},query,q{i}" for i in range(20)]
    manifest = path.with_suffix(".csv")
    manifest.write_text("\n".join(lines) + "\n")
    return manifest


def test_codes_file_streams_the_real_codes_first_and_exact_search_matches_numpy(tmp_path):
    fake_penn(tmp_path / "penn.npz")
    penn = PennCodes.load(tmp_path / "penn.npz")
    gen = CodeGenerator.fit(penn.refs)
    codes = codes_file(tmp_path, 1500, penn, gen)
    assert codes.shape == (1500, 256) and codes.dtype == np.float16
    assert np.allclose(codes[:200], penn.refs, atol=1e-3)
    assert np.allclose(np.linalg.norm(np.asarray(codes, np.float32), axis=1), 1.0, atol=1e-2)
    _, ids = exact_search(codes, 1500, penn.queries, 10)
    full = np.argsort(-(penn.queries @ np.asarray(codes, np.float32).T), axis=1)[:, :10]
    assert (ids[:, 0] == full[:, 0]).all()


def test_true_match_ranks_count_the_codes_above_the_best_true_reference(tmp_path):
    manifest = fake_penn(tmp_path / "penn.npz")
    penn = PennCodes.load(tmp_path / "penn.npz")
    codes = codes_file(tmp_path, 250_000, penn, CodeGenerator.fit(penn.refs))
    truth = find_true_matches(Positions(*penn_positions(manifest)), radius_m=25, region_m=300)
    assert truth.count == 20 and all(list(m) == list(range(5 * i, 5 * i + 5)) for i, m in enumerate(truth.matches))
    noisy = penn.queries + 0.3 * np.random.default_rng(1).standard_normal(penn.queries.shape).astype(np.float32)
    queries = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)  # weak matches, as real ones are at size
    ranks = exact_ranks(codes, 250_000, queries, truth, 200, extent_m=20_000, region_m=300, seed=0)
    # the same by brute force: every code scored, positions drawn chunk by chunk as the bench draws them
    x = np.asarray(codes, np.float32)
    s = queries @ x.T
    best = np.array([s[i, m].max() for i, m in enumerate(truth.matches)])
    xy = np.vstack([distractor_xy(lo, min(100_000, 250_000 - lo), 20_000, 0) for lo in range(0, 250_000, 100_000)])
    inside = np.hstack([truth.near_refs, (((truth.xy[:, None] - xy[None, 200:]) ** 2).sum(axis=2) <= 300**2)])
    for i, m in enumerate(truth.matches):
        s[i, m] = -np.inf  # a true reference never counts against itself
    # A code scoring within float rounding of the best true reference may fall either side of it: the bench
    # scores chunk by chunk, this one matrix product, and BLAS sums them in another order.
    above, tied = s > best[:, None] + TIE, np.abs(s - best[:, None]) <= TIE
    assert (1 + above.sum(axis=1) <= ranks.ranks).all() and (ranks.ranks <= 1 + (above | tied).sum(axis=1)).all()
    low, high = 1 + (above & inside).sum(axis=1), 1 + ((above | tied) & inside).sum(axis=1)
    assert (low <= ranks.region_ranks).all() and (ranks.region_ranks <= high).all()
    assert tied.sum(axis=1).max() <= 20  # a few codes per query at most: the ranks are pinned to within them
    assert (ranks.region_ranks <= ranks.ranks).all() and (ranks.region_ranks < ranks.ranks).any()
    # 250,000 codes over 20 km x 20 km: about 177 within 300 m of a query
    assert 120 < ranks.region_distractors < 240
    assert 0 < recall_at(ranks.ranks)[100] < recall_at(ranks.region_ranks)[100]
    # an index's ranks: the first true reference in its top k; k + 1 where none is there
    found = np.tile(np.arange(10), (20, 1))
    got = found_ranks(found, truth)
    assert got[0] == 1 and got[1] == 6 and (got[2:] == 11).all()
    assert kept(got, np.array([1, 6] + [11] * 18)) == 1.0 and kept(got, np.array([1, 6, 3] + [11] * 17)) == 2 / 3
    assert kept(got, np.full(20, 11)) is None


def test_bench_runs_end_to_end_at_a_tiny_size(tmp_path):
    manifest = fake_penn(tmp_path / "penn.npz")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "bench.index_scale", "--sizes", "2000", "--queries", "30", "--nprobe", "8,32"]
    cmd += ["--shortlist", "50", "--out", str(out), "--penn-codes", str(tmp_path / "penn.npz")]
    cmd += ["--manifest", str(manifest)]
    run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    saved = json.loads((out / "figures.json").read_text())
    kinds = {f["kind"]: f for f in saved["figures"]}
    assert set(kinds) == {"flat (exact)", "ivf-pq32", "ivf-rabitq", "binary flat (exact Hamming)", "binary-ivf"}
    for f in kinds.values():
        assert 0 <= f["recall10"] <= 1 and f["p50_ms"] > 0
    pq = kinds["ivf-pq32"]
    assert pq["params"]["nlist"] == 51 and pq["params"]["nprobe"] in (8, 32)  # 2,000 // 39 lists at most
    assert len(pq["sweep"]) == 2 and pq["ram_bytes_per_ref"] > 0 and pq["add_ms"] > 0 and pq["add_batch_ms"] > 0
    # every list probed: the re-ranked search finds the exact top-10 on the clustered part at least
    assert max(s["recall10"] for s in pq["sweep"]) > min(s["recall10"] for s in pq["sweep"]) - 1e-9
    assert "| 2,000 | ivf-pq32 |" in run.stdout and "## Index kinds" in run.stdout
    true = saved["context"]["true_match"]
    assert true["queries"] == 20 and set(true["sizes"]["2000"]["exact"]) == {"1", "10", "100"}
    assert kinds["flat (exact)"]["true_kept10"] == 1.0 and 0 <= kinds["ivf-rabitq"]["true_r10"] <= 1
    assert all("true_kept10" in s for s in kinds["ivf-rabitq"]["sweep"])
    assert "**The true match**" in run.stdout and "(the service's setting)" not in run.stdout  # nprobe 8, 32
    fid = saved["context"]["fidelity"]  # 200 fake codes span under 256 directions; the generator floors the rest
    assert fid["effective_dim_real"] < fid["effective_dim_synthetic"] and "effective dimension" in run.stdout


def test_effective_dimension_counts_the_directions_codes_vary_in():
    rng = np.random.default_rng(0)
    assert 230 < effective_dimension(rng.standard_normal((20_000, 256))) <= 256
    line = np.outer(rng.standard_normal(5000), rng.standard_normal(256)) + 1e-6 * rng.standard_normal((5000, 256))
    assert effective_dimension(line) < 1.01


@pytest.mark.milvus
def test_bench_measures_the_milvus_kind_on_a_real_server(tmp_path, milvus_server):
    """The milvus kind at a tiny size on the session's Milvus server: filled with positions, sealed and
    indexed, searched (its HNSW at 2,000 codes finds the exact top 10), and in each penn query's region box,
    its changes timed, its collection dropped after."""
    manifest = fake_penn(tmp_path / "penn.npz")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "bench.index_scale", "--sizes", "2000", "--queries", "30", "--nprobe", "8"]
    cmd += ["--shortlist", "50", "--codecs", "RaBitQ", "--no-binary", "--out", str(out)]
    cmd += ["--penn-codes", str(tmp_path / "penn.npz"), "--manifest", str(manifest)]
    cmd += ["--milvus-up-to", "2000", "--milvus-uri", milvus_server.uri]
    run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    kinds = {f["kind"]: f for f in json.loads((out / "figures.json").read_text())["figures"]}
    assert set(kinds) == {"flat (exact)", "ivf-rabitq", "milvus"}
    milvus = kinds["milvus"]
    assert milvus["recall10"] >= 0.9 and milvus["true_kept10"] is not None and 0 <= milvus["true_r10"] <= 1
    assert milvus["add_ms"] > 0 and milvus["remove_ms"] > 0 and milvus["add_batch_ms"] > 0
    assert 0 <= milvus["region_true_r10"] <= 1 and milvus["region_p50_ms"] > 0  # searched in each region's box
    assert "| 2,000 | milvus | HNSW M 32 / ef 256 |" in run.stdout
    assert "milvus in the region's box: R@10 / p50 ms |" in run.stdout
    from pymilvus import MilvusClient

    assert "bench_index_scale_2000" not in MilvusClient(uri=milvus_server.uri).list_collections()
