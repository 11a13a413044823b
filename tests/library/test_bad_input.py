"""Bad input to `geoloc library scan` gets one clear line and exit 2, never a traceback: a path that does
not exist, a file that is not a manifest and a folder with no photo are refused before any model loads (a
models dir that does not exist proves it: loading would fail first); a folder with no geotagged photo (and
a data dir with no collection) after its headers are read, with the skipped files listed."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from app.engine.configs import DEFAULT_CONFIG
from tests.library.conftest import SF


def _scan(folder, data, models) -> subprocess.CompletedProcess:
    args = ["library", "scan", str(folder), "--data-dir", str(data), "--models-dir", str(models),
            "--config", DEFAULT_CONFIG, "--geojson", str(data.parent / "out.geojson")]  # fmt: skip
    return subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=600)


def test_bad_paths_are_refused_before_the_models_load(tmp_path):
    no_models = tmp_path / "no-models"  # nothing to load: a message about models would mean they were loaded
    p = _scan(tmp_path / "missing", tmp_path / "data", no_models)
    assert p.returncode == 2 and "does not exist" in p.stderr, p.stderr
    notes = tmp_path / "notes.csv"
    notes.write_text("a,b\n1,2\n")
    p = _scan(notes, tmp_path / "data", no_models)
    assert p.returncode == 2 and "is not a manifest" in p.stderr, p.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    p = _scan(empty, tmp_path / "data", no_models)
    assert p.returncode == 2 and "holds no photos" in p.stderr and "Traceback" not in p.stderr, p.stderr


@pytest.mark.library
def test_a_folder_with_no_geotagged_photo(tmp_path, library_models):
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    for name in ("q1.jpg", "q2.jpg"):  # San Francisco photos, no GPS
        shutil.copyfile(SF / name, folder / name)
    (folder / "notes.jpg").write_text("not a photo")
    p = _scan(folder, tmp_path / "data", library_models)
    assert p.returncode == 2, p.stdout + p.stderr
    assert "has no photo with GPS and the data dir holds no references" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr and "skipped" in p.stdout and "notes.jpg" in p.stdout
