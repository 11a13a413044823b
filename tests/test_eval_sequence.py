"""`geoloc eval --sequence-window`: a penn walk window held out of a small collection, answered with its
neighbours beside the same photos alone; the manifest's sequence and time columns; the windows."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from app.evaluation.sequences import SequenceWindow, sequences, window_of
from app.manifests import Row, read_manifest, write_manifest
from bench.sequence_walks import step_report, steps, walk_rows, walks
from tests.conftest import PENN
from tests.test_cli import geoloc

CONFIG = "squeezenet-gem"  # global only: the sequence report is what is tested, and it fits in seconds


def _row(name: str, split: str = "query", sequence: str | None = None, time: str | None = None) -> Row:
    return Row(Path(f"/x/{name}.jpg"), 39.95, -75.19, split, name, sequence, time)


def test_query_rows_form_sequences_in_time_order_else_row_order(tmp_path):
    rows = [
        _row("a", sequence="w1", time="2024-09-23T16:10:00-04:00"),
        _row("b", sequence="w2"),
        _row("c", sequence="w1", time="2024-09-23T16:09:00"),  # naive: the sequence's zone
        _row("d", sequence="w2"),
        _row("e", split="db"),
    ]
    path = tmp_path / "m.csv"
    write_manifest(path, rows)
    back = read_manifest(path)
    assert [(r.sequence, r.time) for r in back] == [(r.sequence, r.time) for r in rows]
    got = sequences(back, [0, 1, 2, 3])
    assert got == [([2, 0], [0.0, 60.0]), ([1, 3], [None, None])]
    # Without a sequence column: one sequence, in row order.
    plain = [_row(n) for n in "xyz"]
    write_manifest(path, plain)
    assert "sequence" not in path.read_text().splitlines()[0]
    assert sequences(read_manifest(path), [0, 1, 2]) == [([0, 1, 2], [None, None, None])]


def test_windows_centred_or_online():
    centred, online = SequenceWindow(3), SequenceWindow(3, online=True)
    assert [window_of(p, 5, centred) for p in range(5)] == [(0, 3), (0, 3), (1, 4), (2, 5), (3, 5)]
    assert [window_of(p, 5, online) for p in range(5)] == [(0, 1), (0, 2), (0, 3), (1, 4), (2, 5)]


def test_the_walk_manifest_holds_whole_windows_out():
    rows = walk_rows(PENN, window=6, part=0, parts=3)
    queries = [r for r in rows if r.split == "query"]
    held = {r.group for r in queries}
    assert queries and all(r.sequence and r.time for r in queries)
    assert not any(r.group in held for r in rows if r.split == "db")  # neither the photo nor its crops
    assert all(r.image.parent.name == "photos" for r in queries)
    for name in {r.sequence for r in queries}:
        assert 2 <= sum(r.sequence == name for r in queries) <= 6


def test_eval_reports_the_sequence_beside_the_photos_alone(tmp_path, models_dir, penn_index):
    captures = [r for r in penn_index if r["photo"]][:40]
    walk = captures[12:18]
    rows = []
    for r in captures:
        if r in walk:
            time = f"2024-09-23T16:{10 + walk.index(r):02d}:00-04:00"
            rows.append(Row(PENN / r["photo"], float(r["lat"]), float(r["lon"]), "query", r["photo_id"], "w", time))
            continue
        for img in [r["photo"]] + r["crops"].split(";")[:2]:
            rows.append(Row(PENN / img, float(r["lat"]), float(r["lon"]), "db", r["photo_id"]))
    manifest = tmp_path / "walk.csv"
    write_manifest(manifest, rows)
    out = tmp_path / "eval.json"
    # The three runs read one extraction of the photos (--cache: the features are the same for each run).
    where = ["--config", CONFIG, "--models-dir", str(models_dir), "--cache", str(tmp_path / "features")]
    args = ["eval", "-m", str(manifest), *where, "--json", str(out)]
    p = geoloc(*args, "--sequence-window", "3", "--max-speed-mps", "1.5", "--max-step-m", "100")
    assert "sequences: windows of 3 photos, centred" in p.stdout
    assert "Recall@1/5, sequence vs alone" in p.stdout
    report = json.loads(out.read_text())
    assert report["n_query"] == 6
    seq = report["sequence"]
    assert seq["window"] == 3 and not seq["online"] and seq["photos"] == 6 and seq["max_speed_mps"] == 1.5
    assert set(report["recall_at"]) == set(report["single_recall_at"]) == {"1", "5", "10", "20"}
    assert report["answers"] is not None and report["single_answers"] is not None
    # The fold's collection was calibrated on its own walks too: its db photos' EXIF times.
    (walks,) = [c["sequence"] for c in report["calibration_per_fold"]]
    assert walks["window"] == 5 and walks["walks"] >= 2 and walks["photos"] <= 5 * walks["walks"]
    assert 0 <= walks["confident_alone"] <= walks["photos"]
    # The photos alone are what a run without sequences reports.
    alone = tmp_path / "alone.json"
    geoloc(*args[:-1], str(alone))
    plain = json.loads(alone.read_text())
    assert plain["recall_at"] == report["single_recall_at"] and plain["sequence"] is None
    p = geoloc(*args, "--sequence-window", "3", "--online")
    assert "centred" not in p.stdout and "online" in p.stdout


def test_the_walks_steps_are_measured_against_the_motion_models_defaults():
    """`python -m bench.sequence_walks --steps` on the penn walks: every consecutive pair of a camera's
    photos, in time order, and the defaults the docs say hold them all."""
    done = subprocess.run(
        [sys.executable, "-m", "bench.sequence_walks", "--steps", "--source", str(PENN)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    by_camera = walks(PENN)
    measured = steps(PENN)
    assert len(measured) == sum(len(photos) - 1 for photos in by_camera.values()) > 50
    assert all(gap >= 0 for gap, _ in measured)
    lines = done.stdout.splitlines()
    assert lines[0] == f"{len(measured)} steps (consecutive photos of one camera)"
    assert lines[4].startswith("beyond the speed bound (2.0 m/s x gap + 50 m): ") and lines[4].endswith(": 0")
    assert lines[5].startswith("beyond the step bound (150 m + 50 m): ") and lines[5].endswith(": 0")
    assert lines[6].endswith("of which more than 25 m apart: 0")
    # The counts count: one step too fast for its gap, one past the step bound, two close in time but apart.
    made = step_report([(10.0, 100.0), (0.0, 30.0), (5.0, 10.0), (400.0, 210.0)]).splitlines()
    assert made[0].startswith("4 steps") and made[4].endswith(": 1") and made[5].endswith(": 1")
    assert made[6].endswith("within 10 s: 3, of which more than 25 m apart: 2")
