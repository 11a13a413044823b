"""The index-scale benchmark runs end to end at a tiny size and reports figures that mean what they say."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.scale_codes import CodeGenerator, PennCodes, codes_file, effective_dimension, exact_search

REPO = Path(__file__).resolve().parents[1]


def fake_penn(path: Path) -> None:
    """Stand-in for the cached real codes (a fresh clone has no fitted pipeline): clustered unit codes."""
    rng = np.random.default_rng(0)
    centres = rng.standard_normal((40, 256)).astype(np.float32)
    refs = centres[np.repeat(np.arange(40), 5)] + rng.standard_normal((200, 256)).astype(np.float32)
    queries = centres[:20] + rng.standard_normal((20, 256)).astype(np.float32)
    PennCodes(
        refs / np.linalg.norm(refs, axis=1, keepdims=True), queries / np.linalg.norm(queries, axis=1, keepdims=True)
    ).save(path)


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


def test_bench_runs_end_to_end_at_a_tiny_size(tmp_path):
    fake_penn(tmp_path / "penn.npz")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "bench.index_scale", "--sizes", "2000", "--queries", "30", "--nprobe", "8,32"]
    cmd += ["--shortlist", "50", "--out", str(out), "--penn-codes", str(tmp_path / "penn.npz")]
    run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    saved = json.loads((out / "figures.json").read_text())
    kinds = {f["kind"]: f for f in saved["figures"]}
    assert set(kinds) == {"flat (exact)", "ivf-pq32", "ivf-rabitq", "binary flat (exact Hamming)", "binary-ivf"}
    for f in kinds.values():
        assert 0 <= f["recall10"] <= 1 and f["p50_ms"] > 0
    pq = kinds["ivf-pq32"]
    assert pq["params"]["nlist"] == 51 and pq["params"]["nprobe"] in (8, 32)  # 2,000 // 39 lists at most
    assert len(pq["sweep"]) == 2 and pq["ram_bytes_per_ref"] > 0 and pq["add_ms"] > 0
    # every list probed: the re-ranked search finds the exact top-10 on the clustered part at least
    assert max(s["recall10"] for s in pq["sweep"]) > min(s["recall10"] for s in pq["sweep"]) - 1e-9
    assert "| 2,000 | ivf-pq32 |" in run.stdout and "## Index kinds" in run.stdout
    fid = saved["context"]["fidelity"]  # 200 fake codes span under 256 directions; the generator floors the rest
    assert fid["effective_dim_real"] < fid["effective_dim_synthetic"] and "effective dimension" in run.stdout


def test_effective_dimension_counts_the_directions_codes_vary_in():
    rng = np.random.default_rng(0)
    assert 230 < effective_dimension(rng.standard_normal((20_000, 256))) <= 256
    line = np.outer(rng.standard_normal(5000), rng.standard_normal(256)) + 1e-6 * rng.standard_normal((5000, 256))
    assert effective_dimension(line) < 1.01
