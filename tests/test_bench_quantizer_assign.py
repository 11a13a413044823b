"""bench.quantizer_assign runs on real FAISS at a small size: the exact quantizer always assigns a code to
its nearest list, an HNSW row per efSearch, each add removed again."""

import numpy as np

from bench.quantizer_assign import one_nlist


def test_exact_and_graph_rows():
    rng = np.random.default_rng(0)
    exact = one_nlist(64, [2000], [None], 50, rng)
    graph = one_nlist(64, [2000], [16, 64], 50, rng)
    assert [r["how"] for r in exact] == ["exact"] and exact[0]["agree"] == 1.0
    assert [r["how"] for r in graph] == ["hnsw efSearch 16", "hnsw efSearch 64"]
    assert all(r["add_ms"] > 0 and r["nlist"] == 64 and r["fill"] == 2000 for r in exact + graph)
    assert 0.0 < graph[0]["agree"] <= graph[1]["agree"] <= 1.0
