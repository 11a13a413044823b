"""The layout change (issue 19) changed no answer: the code of the commit before it, taken from git history,
and the code of today fit, ingest and locate the same penn photos through the same CLI commands, on this
machine, and must agree (same fitted state, same ids, scores within 1e-6; since issue 22 answers round
their scores and metres and write capture times in ISO 8601 with the EXIF zone, and the old answers are
read that way).

Why run the old code rather than compare with stored answers: both sides then share the machine, the
libraries and the converted model, so any difference is the code's.

Since issue 21 the answers change on purpose (queries, references and fitting decode at the scale the
pipeline reads, ``Pipeline.decode``; keypoint sampling in float32), so the "after" side is main as the
layout change left it (``AFTER``), also from git history: the claim stays the layout change's alone, and
both sides' answers are read as today's code writes them (``_as_today``). The
new front end is checked by tests/engine/test_pipeline_decode.py and its recall by docs/RESULTS.md."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from tests.conftest import REPO, penn_photo

#: main just before the layout change: the hardening of issue 18 merged, nothing of issue 19.
BEFORE = "7150a8d8d88842dfdb0802a40d5f67da14f0ca6f"
#: main with the layout change (issue 19) merged, just before issue 21 changed the decode scale.
AFTER = "e6f641d2cf5967e03d0523fdb7c9d0432fb8fa14"
CONFIG = "hybrid-bin"
QUERIES = ["img_00001.jpg", "img_00006.jpg", "img_00011.jpg"]  # the mini manifest's query captures


def _old_code(tmp: Path, commit: str = BEFORE) -> Path:
    """The ``app`` package as it was at ``commit``, unpacked from git history."""
    archive = tmp / f"{commit}.tar"
    out = subprocess.run(
        ["git", "-C", str(REPO), "archive", "--format=tar", "-o", str(archive), commit, "app"],
        capture_output=True, text=True,
    )  # fmt: skip
    if out.returncode != 0:
        pytest.fail(f"commit {commit} is not in this clone's history (a shallow clone?): {out.stderr}")
    root = tmp / commit
    with tarfile.open(archive) as tar:
        tar.extractall(root, filter="data")
    return root


def _cli(code_root: Path, *args: str) -> str:
    """``python -m app.cli ARGS`` with ``code_root``'s ``app`` first on the path (its cwd)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "GEOLOC_ORT_THREADS": "1", "PYTHONPATH": str(code_root)}
    out = subprocess.run(
        [sys.executable, "-m", "app.cli", *args], cwd=code_root, capture_output=True, text=True, timeout=900, env=env
    )
    assert out.returncode == 0, f"{code_root.name}: geoloc {' '.join(args)}\n{out.stdout}\n{out.stderr}"
    return out.stdout


def _run_side(code_root: Path, work: Path, models_dir: Path, manifest: Path) -> dict:
    """Fit, ingest the db rows, locate the query photos (with and without verification): what a user runs."""
    models = work / "models"
    models.mkdir(parents=True)
    shutil.copy(models_dir / "squeezenet1_1.onnx", models / "squeezenet1_1.onnx")
    data = work / "data"
    common = ["--models-dir", str(models), "--config", CONFIG]
    _cli(code_root, "fit", "--manifest", str(manifest), "--svm-bank", "none", *common)
    _cli(
        code_root,
        "ingest",
        "--manifest",
        str(manifest),
        "--split",
        "db",
        "--workers",
        "1",
        "--data-dir",
        str(data),
        *common,
    )
    fitted = json.loads((models / "pipelines" / CONFIG / "pipeline.json").read_text())
    answers = {}
    for name in QUERIES:
        for rerank in ([], ["--rerank"]):
            out = _cli(
                code_root, "locate", str(penn_photo(name)), "--top-k", "5", *rerank, "--data-dir", str(data), *common
            )
            answer = json.loads(out)
            answer.pop("timings_ms", None)
            answers[f"{name}{rerank}"] = answer
    return {"fitted": {k: fitted.get(k) for k in ("float_dim", "bits", "n_train_images")}, "answers": answers}


#: Fields that answers round since issue 22 (app/api/schemas.py), with one unit of their last digit: the
#: old side's values are rounded the same way before the comparison, and may differ by that unit where the
#: old answer had already rounded (scores to 6 digits) just across a boundary.
ROUNDED = {"score": 4, "p_within_25m": 4, "confidence": 4, "distance_m": 1, "radius_m": 1}


def _as_today(value, key: str = ""):
    """An answer as today's code writes it: rounded fields rounded, capture times in ISO 8601."""
    from app.text import iso_or_as_stored

    if isinstance(value, dict):
        return {k: _as_today(v, k) for k, v in value.items()}
    if isinstance(value, list):
        return [_as_today(v, key) for v in value]
    if key in ROUNDED and isinstance(value, float):
        return round(value, ROUNDED[key])
    if key == "captured_at" and isinstance(value, str):
        return iso_or_as_stored(value)
    return value


def _close(a, b, path: str = "", key: str = "") -> list[str]:
    """Where two JSON values differ: floats beyond 1e-6 (relative to their size; a rounded field by more than
    one unit of its last digit), anything else at all."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{path}: keys {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in _close(a[k], b[k], f"{path}.{k}", k)]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} against {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in _close(x, y, f"{path}[{i}]", key)]
    if isinstance(a, float) and isinstance(b, float):
        tolerance = 1.01 * 10 ** -ROUNDED[key] if key in ROUNDED else 1e-6 * max(1.0, abs(a))
        return [] if abs(a - b) <= tolerance else [f"{path}: {a} against {b}"]
    if key == "captured_at" and isinstance(a, str) and isinstance(b, str):
        # Since issue 22 the photo's EXIF OffsetTimeOriginal is kept as the zone: the same time, with "-04:00".
        return [] if re.fullmatch(re.escape(a) + r"([+-]\d{2}:\d{2})?", b) else [f"{path}: {a!r} against {b!r}"]
    return [] if a == b else [f"{path}: {a!r} against {b!r}"]


def test_fit_ingest_and_locate_answer_as_before_the_layout_change(tmp_path, models_dir, mini_manifest):
    before = _run_side(_old_code(tmp_path), tmp_path / "old", models_dir, mini_manifest)
    after = _run_side(_old_code(tmp_path, AFTER), tmp_path / "new", models_dir, mini_manifest)
    assert before["fitted"] == after["fitted"]
    assert any(a["candidates"] for a in after["answers"].values())
    assert _close(_as_today(before["answers"]), _as_today(after["answers"])) == []
