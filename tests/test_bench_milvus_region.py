"""bench.milvus_region on the session's real Milvus at a small size: both ways of searching a box (and the
filtered HNSW at another ef) return rows, the replica's exact scoring finds the box's exact top 10, and the
collection is dropped after."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.milvus
def test_both_ways_of_searching_a_box_are_measured(milvus_server):
    cmd = [sys.executable, "-m", "bench.milvus_region", "--codes", "3000", "--sides", "0.1,0.5", "--queries", "5"]
    cmd += ["--ef", "64"]  # one more column: the filtered HNSW at another ef
    run = subprocess.run(
        [*cmd, "--milvus-uri", milvus_server.uri], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    rows = [line.split(" | ") for line in run.stdout.splitlines() if line.startswith("| 0.")]
    assert [r[0] for r in rows] == ["| 0.1", "| 0.5"]
    for r in rows:
        assert 0 < int(r[1].replace(",", "")) < 3000
        assert float(r[3]) == 1.0  # the replica's exact scoring: the box's exact top 10
        assert 0.0 <= float(r[5]) <= 1.0 and float(r[2]) > 0 and float(r[4]) > 0
        assert float(r[6]) > 0 and 0.0 <= float(r[7].rstrip(" |")) <= 1.0  # at ef 64
    # A box of a quarter of the codes, searched at the kind's filtered ef (above the 3,000 codes): found whole.
    assert float(rows[1][5]) >= 0.9, rows[1]
    from pymilvus import MilvusClient

    assert "bench_milvus_region" not in MilvusClient(uri=milvus_server.uri).list_collections()
