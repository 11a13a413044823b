"""`geoloc ingest SOURCE` as a user runs it: a folder of photos (EXIF GPS), photos without GPS, bad files,
the resume journal, a CSV of rows, and a running server that sees what the run adds."""

import csv
import importlib.util
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from app.storage.store import NewReference, ReferenceStore
from tests.api.conftest import CONFIG, Server
from tests.conftest import PENN

#: Photos with EXIF GPS; img_00033 also has a GPSImgDirection (heading).
GPS_PHOTOS = ("img_00000.jpg", "img_00002.jpg", "img_00033.jpg")
#: Below the 2.7 MB full-size original, above the 1600 px photos (about 0.8 MB).
MAX_BYTES = 2_000_000


def ingest(source: Path, data: Path, models: Path, *extra: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "GEOLOC_ORT_THREADS": "1", "GEOLOC_MAX_UPLOAD_BYTES": str(MAX_BYTES)}
    args = ["ingest", str(source), "--config", CONFIG, "--data-dir", str(data), "--models-dir", str(models), *extra]
    p = subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, f"geoloc ingest failed ({p.returncode}):\n{p.stdout}\n{p.stderr}"
    return p


def rows(data: Path) -> dict[str, tuple]:
    db = sqlite3.connect(data / "references.sqlite")
    try:
        got = db.execute("SELECT label, lat, lon, heading, captured_at, source, status FROM refs").fetchall()
    finally:
        db.close()
    return {r[0]: r[1:] for r in got}


def report(stdout: str) -> dict[str, str]:
    line = next(s for s in stdout.splitlines() if s.startswith("report of the files not ingested: "))
    with open(line.split(": ", 1)[1], newline="") as f:
        return {Path(r["path"]).name: r["reason"] for r in csv.DictReader(f)}


@pytest.fixture
def photo_folder(tmp_path) -> Path:
    """Three GPS photos in nested folders, a photo without EXIF, and three bad files."""
    src = tmp_path / "photos"
    (src / "day1" / "walk").mkdir(parents=True)
    shutil.copy(PENN / "photos" / GPS_PHOTOS[0], src / GPS_PHOTOS[0])
    shutil.copy(PENN / "photos" / GPS_PHOTOS[1], src / "day1" / GPS_PHOTOS[1])
    shutil.copy(PENN / "photos" / GPS_PHOTOS[2], src / "day1" / "walk" / GPS_PHOTOS[2])
    crop = cv2.imread(str(PENN / "crops" / "img_00005_0.jpg"))
    assert cv2.imwrite(str(src / "day1" / "no_exif.jpg"), crop)  # OpenCV writes no EXIF
    data = (PENN / "photos" / "img_00004.jpg").read_bytes()
    (src / "truncated.jpg").write_bytes(data[: len(data) // 3])
    (src / "day1" / "notes.jpg").write_text("shopping list, not a photo\n")
    shutil.copy(PENN / "photos-full" / "img_00000.jpg", src / "day1" / "full_size.jpg")  # 2.7 MB > MAX_BYTES
    (src / "other.txt").write_text("not a photo name: not read at all")
    return src


def test_a_folder_of_photos_is_ingested_at_their_exif_positions(photo_folder, tmp_path, fitted_models, penn_index):
    data = tmp_path / "data"
    heic = photo_folder / "phone.heic"
    heic.write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00" + b"\x00" * 64)
    out = ingest(photo_folder, data, fitted_models)
    assert "ingested 3 new references (0 already present, 5 skipped)" in out.stdout
    truth = {r["photo"].split("/")[-1]: (float(r["lat"]), float(r["lon"])) for r in penn_index if r["photo"]}
    got = rows(data)
    assert set(got) == set(GPS_PHOTOS)
    for name in GPS_PHOTOS:
        lat, lon, heading, captured_at, source, status = got[name]
        assert (lat, lon) == pytest.approx(truth[name], abs=2e-5), name  # EXIF GPS, as index.csv has it
        # EXIF's DateTimeOriginal ("2024:09:23 ..."), stored as ISO 8601
        assert source == "folder" and status == "indexed" and captured_at.startswith("2024-09-23T")
    assert got["img_00033.jpg"][2] == pytest.approx(39.2569847, abs=1e-6)  # EXIF GPSImgDirection
    assert got["img_00000.jpg"][2] is None

    skipped = report(out.stdout)
    assert set(skipped) == {"no_exif.jpg", "truncated.jpg", "notes.jpg", "full_size.jpg", "phone.heic"}
    assert "no GPS position" in skipped["no_exif.jpg"]
    assert "truncated" in skipped["truncated.jpg"]
    assert "not a JPEG" in skipped["notes.jpg"]
    assert f"the limit is {MAX_BYTES}" in skipped["full_size.jpg"]
    heif_installed = importlib.util.find_spec("pillow_heif") is not None
    assert heif_installed or skipped["phone.heic"] == "HEIC unsupported: pip install pillow-heif"
    assert "1 no GPS in EXIF" in out.stdout and "1 too large" in out.stdout and "1 not an image" in out.stdout
    assert "ingest folder: 8/8 img" in out.stderr  # the last progress line (stderr is not a terminal)
    db = sqlite3.connect(data / "references.sqlite")
    assert db.execute("SELECT COUNT(*) FROM claims").fetchone()[0] == 0  # released at the end of the run
    db.close()


def test_a_rerun_skips_unchanged_files_through_the_journal_without_reading_them(photo_folder, tmp_path, fitted_models):
    data = tmp_path / "data"
    ingest(photo_folder, data, fitted_models)
    stored = [photo_folder / GPS_PHOTOS[0], photo_folder / "day1" / GPS_PHOTOS[1]]
    for path in stored:  # same size and mtime, other bytes: a re-run that read them would find no image
        st = path.stat()
        path.write_bytes(b"\x00" * st.st_size)
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    touched = photo_folder / "day1" / "walk" / GPS_PHOTOS[2]  # same bytes, new mtime: read, and a duplicate
    st = touched.stat()
    os.utime(touched, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))

    again = ingest(photo_folder, data, fitted_models)
    assert "ingested 0 new references (3 already present, 4 skipped)" in again.stdout
    assert "2 files unchanged since an earlier run were not read again" in again.stdout
    assert set(report(again.stdout)) == {"no_exif.jpg", "truncated.jpg", "notes.jpg", "full_size.jpg"}
    assert len(rows(data)) == 3


def test_a_csv_of_rows_with_paths_relative_to_it(tmp_path, fitted_models):
    src = tmp_path / "survey"
    (src / "crops").mkdir(parents=True)
    for name in ("img_00010_0.jpg", "img_00011_0.jpg", "img_00012_0.jpg"):
        shutil.copy(PENN / "crops" / name, src / "crops" / name)
    (src / "list.csv").write_text(
        "image,lat,lon,heading,captured_at,label\n"
        "crops/img_00010_0.jpg,39.9517,-75.1921,90,2024-09-23T16:00:00,north gate\n"
        "crops/img_00011_0.jpg,39.9518,-75.1922,,,\n"
        "crops/img_00012_0.jpg,123,-75.1922,,,\n"
        "crops/missing.jpg,39.9518,-75.1922,,,\n"
    )
    data = tmp_path / "data"
    out = ingest(src / "list.csv", data, fitted_models)
    assert "ingested 2 new references (0 already present, 2 skipped)" in out.stdout
    got = rows(data)
    assert got["north gate"][:5] == (39.9517, -75.1921, 90.0, "2024-09-23T16:00:00", "csv")
    assert got["img_00011_0.jpg"][:2] == (39.9518, -75.1922) and got["img_00011_0.jpg"][2] is None
    skipped = report(out.stdout)
    assert "out of range" in skipped["img_00012_0.jpg"] and "cannot read the file" in skipped["missing.jpg"]

    store = ReferenceStore(data)  # a reference deleted since: its journal entry no longer counts
    (deleted,) = [r.id for r in store.list()[0] if r.label == "north gate"]
    assert store.delete(deleted)
    store.close()
    again = ingest(src / "list.csv", data, fitted_models)
    assert "ingested 1 new references (1 already present, 2 skipped)" in again.stdout
    assert "1 files unchanged since an earlier run" in again.stdout and "north gate" in rows(data)


def test_rows_a_crashed_run_left_claimed_are_encoded_once_the_lease_is_over(tmp_path, fitted_models):
    data = tmp_path / "data"
    store = ReferenceStore(data)
    crops = [PENN / "crops" / f"img_0002{n}_0.jpg" for n in range(3)]
    ids = [i for i, _ in store.add_many([NewReference(p.read_bytes(), "jpeg", 39.95, -75.19) for p in crops])[0]]
    store.claim(ids[:2], "a-run-that-crashed", lease_s=0)  # its lease is over
    store.claim(ids[2:], "a-run-still-going", lease_s=600)
    store.close()
    empty = tmp_path / "empty.csv"
    empty.write_text("image,lat,lon\n")
    out = ingest(empty, data, fitted_models)
    assert "also encoded 2 rows left pending by earlier runs" in out.stdout
    store = ReferenceStore(data)
    assert [store.get(i).status for i in ids] == ["indexed", "indexed", "pending"]  # the live claim is kept
    store.close()


def test_a_running_server_sees_what_the_run_encodes(tmp_path, fitted_models, mini_manifest):
    """With a server's worker holding the data dir, the run still encodes the rows it claimed; the server
    catches up from the change log."""
    data = tmp_path / "data"
    with Server(data, fitted_models) as s:
        out = ingest(mini_manifest, data, fitted_models, "--split", "train")
        assert "a server's worker runs on this data dir" in out.stdout and "ingested 9 new references" in out.stdout
        assert s.client.get("/ready").json()["index_size"] == 9
        listed = s.client.get("/references").json()
        assert listed["total"] == 9 and {r["source"] for r in listed["items"]} == {"manifest"}
