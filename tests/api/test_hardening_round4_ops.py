"""Operations that said "ok" or left things out (hardening, round 4), through the real `geoloc` command:

- `geoloc backup` and `geoloc restore` carry the photo library's journal and its write-back copies, so a
  write made before the backup is undone from the restored data dir, photo back byte for byte, even when
  the data dir it was made in is gone;
- `geoloc check` reads every stored features file (its CRC): a bit-flipped, a truncated and an emptied one
  are named, `geoloc features backfill` remakes exactly those, and `check` is then clean;
- `geoloc check` names a database of a newer schema (which the server refuses), and never says that
  `--repair` removes what it then leaves (a folder in images/);
- a refit that continues an interrupted re-index names the SVM bank of the pipeline it switches to.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from app.jobs.refit import RefitOptions, fit_generation, reindex
from app.storage.migrations import SchemaTooNew
from app.storage.store import ReferenceStore
from tests.api.conftest import CONFIG
from tests.api.test_stored_features_ops import PROFILE, sv_collection  # noqa: F401  (the module's fixture)
from tests.conftest import PENN


def geoloc(*args: str) -> subprocess.CompletedProcess:
    """The real command line, in a process of its own; the caller checks the exit code."""
    return subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=600)


def ok(*args: str) -> str:
    done = geoloc(*args)
    assert done.returncode == 0, f"geoloc {' '.join(args)}: {done.returncode}\n{done.stdout}\n{done.stderr}"
    return done.stdout


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_restored_data_dir_undoes_a_library_write(mini_collection, fitted_models, tmp_path):
    if shutil.which("exiftool") is None:
        pytest.fail("exiftool is missing: `make test` installs Debian's libimage-exiftool-perl")
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    lib = tmp_path / "lib"
    lib.mkdir()
    photo = lib / "no-gps.jpg"
    shutil.copyfile(PENN / "photos" / "img_00036.jpg", photo)
    subprocess.run(["exiftool", "-q", "-q", "-overwrite_original", "-gps:all=", str(photo)], check=True)
    original = sha(photo)
    where = ["--data-dir", str(data)]
    ok("library", "scan", str(lib), *where, "--models-dir", str(fitted_models), "--config", CONFIG, "--workers", "1")
    ok("library", "decide", str(lib), str(photo), "move", "--lat", "39.95", "--lon", "-75.19", *where)
    assert "1 wrote" in ok("library", "write", str(lib), "--in-file", *where)
    assert sha(photo) != original  # the GPS is in the photo now; its original bytes are in the data dir only

    backup = tmp_path / "backup"
    backed_up = ok("backup", str(backup), *where)
    restored = tmp_path / "restored"
    restored_out = ok("restore", str(backup), "--data-dir", str(restored))
    shutil.rmtree(data)  # the disk it lived on is gone: the restored copy alone must undo the write

    out = ok("library", "undo", str(lib), "--data-dir", str(restored))
    assert "1 writes undone" in out, out
    assert sha(photo) == original
    assert "the library journal and 1 write-back copies" in backed_up, backed_up
    assert "with the library journal and 1 write-back copies" in restored_out, restored_out
    for folder in (backup, restored):  # the photos' original bytes: as private as the rest of the data dir
        assert (folder / "library-backups").stat().st_mode & 0o777 == 0o700
        assert (folder / "library.sqlite").stat().st_mode & 0o777 == 0o600


def _damage(files, shas: list[str]) -> None:
    """One bit flipped in the arrays, the file cut in the middle, the file emptied."""
    flipped, cut, emptied = (files.path(s) for s in shas)
    data = bytearray(flipped.read_bytes())
    data[-1] ^= 0x01
    flipped.write_bytes(bytes(data))
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    emptied.write_bytes(b"")


def test_check_reads_the_stored_features_and_backfill_remakes_the_damaged(sv_collection, tmp_path):  # noqa: F811
    from app.storage.feature_files import FeatureFiles, profile_root

    models, source, _ = sv_collection
    data = tmp_path / "data"
    shutil.copytree(source, data)
    files = FeatureFiles(profile_root(data, PROFILE))
    before = {s: files.read(s) for s in files.names()}
    damaged = sorted(before)[2:5]
    _damage(files, damaged)
    where = ["--data-dir", str(data), "--models-dir", str(models)]

    check = geoloc("check", *where)
    assert check.returncode == 1, check.stdout + check.stderr
    assert "3 damaged" in check.stdout, check.stdout
    for s in damaged:
        assert s in check.stderr, check.stderr
    assert "checksum mismatch" in check.stderr and "shorter than the" in check.stderr, check.stderr

    out = ok("features", "backfill", *where)
    assert "3 written (3 of them in place of a damaged file), 7 already there, 0 failed" in out, out
    assert {s: files.read(s) for s in files.names()} == before  # the bytes ingestion wrote, and only those
    assert "ok:" in ok("check", *where)


def test_check_names_a_schema_newer_than_the_code(mini_collection, fitted_models, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    with sqlite3.connect(data / "references.sqlite") as db:
        db.execute("INSERT INTO schema_versions(version, name, applied_at) VALUES (99, 'future', 'then')")
    db.close()
    with pytest.raises(SchemaTooNew):  # what the server meets when it opens the data dir
        ReferenceStore(data)
    check = geoloc("check", "--data-dir", str(data), "--models-dir", str(fitted_models))
    assert check.returncode == 1, check.stdout + check.stderr
    assert "schema version 99" in check.stderr and "newer version of geoloc" in check.stderr, check.stderr


def test_check_never_says_repair_removes_what_it_leaves(mini_collection, fitted_models, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    stray = data / "images" / "holiday"
    stray.mkdir()
    where = ["--data-dir", str(data), "--models-dir", str(fitted_models)]
    first = geoloc("check", *where)
    assert first.returncode == 1 and "holiday" in first.stderr, first.stdout + first.stderr
    repaired = geoloc("check", "--repair", "--min-age", "0", *where)
    assert stray.is_dir()  # the sweep removes regular files only
    # So no problem naming it may promise that --repair removes it.
    for line in first.stderr.splitlines() + repaired.stderr.splitlines():
        assert not ("holiday" in line and "--repair` removes" in line), line
    assert "holiday" in repaired.stderr and "by hand" in repaired.stderr, repaired.stderr


def test_a_resumed_refit_names_the_bank_of_its_pipeline(mini_collection, fitted_models, tmp_path):
    """The refit is interrupted as ``test_refit`` interrupts one (its re-index stopped part-way, as a killed
    process leaves it), then `geoloc refit` continues it in a process that never ran the fit."""
    from app.engine.imageio import ImageLimits
    from app.ingestion.encoding.local import LocalEngine

    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    store = ReferenceStore(data)
    target, summary = fit_generation(store, fitted_models, RefitOptions(sample=20, svm_bank="collection", seed=1))
    assert summary.bank == "collection"
    store.start_reindex(target)
    engine = LocalEngine(target.source(data, fitted_models).load(), ImageLimits())
    assert reindex(store, target, engine, batch=3, limit=6) == (6, 0)  # then the process dies
    store.close()
    assert json.loads((data / target.pipeline / "pipeline.json").read_text())["svm_bank_source"] == "collection"

    out = ok("refit", "--data-dir", str(data), "--models-dir", str(fitted_models))
    assert "continued an interrupted re-index" in out and "24 references re-encoded" in out, out
    assert "SVM bank: collection" in out, out
