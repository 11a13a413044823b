"""bench.quantizer_assign runs on real FAISS at a small size: the exact quantizer always assigns a code to
its nearest list (one at a time and in batches), an HNSW row per efSearch and an 8-bit scan with exact
re-scoring, each add removed again."""

import numpy as np

from bench.quantizer_assign import one_nlist


def test_exact_graph_and_refine_rows():
    rng = np.random.default_rng(0)
    rows = one_nlist(64, [2000], ["exact", "hnsw", "sq8-refine 8"], [16, 64], 50, 10, rng)
    assert [r["how"] for r in rows] == ["exact", "hnsw efSearch 16", "hnsw efSearch 64", "sq8-refine 8"]
    exact, graph16, graph64, refine = rows
    assert exact["agree"] == 1.0 and exact["batch_ms"] > 0
    assert all(r["add_ms"] > 0 and r["nlist"] == 64 and r["fill"] == 2000 for r in rows)
    assert graph16["batch_ms"] is None and refine["batch_ms"] is None
    assert 0.0 < graph16["agree"] <= graph64["agree"] <= 1.0 and 0.0 < refine["agree"] <= 1.0


def test_the_command_prints_every_row_against_the_exact_add_at_the_fewest_lists(monkeypatch, capsys):
    from bench import quantizer_assign

    flags = ["--nlists", "64,128", "--fills", "2000", "--ef", "16", "--refine", "8", "--adds", "20", "--batch", "10"]
    monkeypatch.setattr("sys.argv", ["quantizer_assign", *flags])
    quantizer_assign.main()
    table = [
        line for line in capsys.readouterr().out.splitlines() if line.startswith("| 64 |") or line.startswith("| 128 |")
    ]
    assert [line.split(" | ")[2] for line in table] == ["exact", "hnsw efSearch 16", "sq8-refine 8"] * 2
    assert table[0].split(" | ")[4] == "1.0x" and table[0].split(" | ")[6] == "1.0x"
