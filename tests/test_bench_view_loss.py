"""bench.view_loss gives each query the database geoloc eval gives it (the same folds, groups kept apart)."""

from __future__ import annotations

from pathlib import Path

from app.evaluation.datasets import Row
from bench.view_loss import query_databases


def _rows() -> list[Row]:
    rows = []
    for g in range(10):
        for k in range(3):  # a photo and two crops: one capture
            rows.append(Row(Path(f"g{g}_{k}.jpg"), 40.0 + g * 1e-4, -75.0, "train" if g == 9 else "db", f"g{g}"))
    rows[0] = Row(rows[0].image, rows[0].lat, rows[0].lon, "query", "g0")
    return rows


def test_every_non_train_row_is_a_query_once_and_never_meets_its_capture() -> None:
    rows = _rows()
    pairs = query_databases(rows, folds=5)
    assert sorted(q for q, _ in pairs) == [i for i, r in enumerate(rows) if r.split != "train"]
    for q, db in pairs:
        assert all(rows[j].group != rows[q].group and rows[j].split != "train" for j in db)
        assert len(db) >= 3 * 9 - 3 * 2 - 3  # the other folds' captures (one or two per fold), no train rows


def test_one_fold_is_the_manifests_split() -> None:
    rows = _rows()
    pairs = query_databases(rows, folds=1)
    assert [q for q, _ in pairs] == [0, 1, 2]  # the query row's capture: its group is the query side
    assert all(rows[j].group != "g0" for j in pairs[0][1])
