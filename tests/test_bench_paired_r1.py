"""bench.paired_r1 counts the queries whose first candidate became right or wrong, matched query by query."""

from __future__ import annotations

import json
from pathlib import Path

from bench.paired_r1 import paired, sign_test


def _run(path: Path, firsts: list[tuple[float, float]]) -> Path:
    queries = [
        {"image": f"q{i}.jpg", "fold": 1, "lat": 40.0 + i * 1e-3, "lon": -75.0, "candidates": [list(c)]}
        for i, c in enumerate(firsts)
    ]
    path.write_text(json.dumps({"radius_m": 25.0, "queries": queries}))
    return path


def test_wins_losses_and_the_sign_test(tmp_path) -> None:
    right = [(40.0 + i * 1e-3, -75.0) for i in range(4)]
    wrong = (41.0, -75.0)  # over 100 km from every query
    base = _run(tmp_path / "a.json", [right[0], right[1], wrong, wrong])
    variant = _run(tmp_path / "b.json", [right[0], wrong, right[2], right[3]])
    assert paired(base, variant) == {"queries": 4, "wins": 2, "losses": 1, "p": 1.0}
    assert round(sign_test(5, 0), 4) == 0.0625 and round(sign_test(51, 47), 2) == 0.76  # results.md's figures
