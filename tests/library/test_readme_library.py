"""The "Geolocating a photo library" lines of docs/guide.md, run as written in a shell on real photos:
penn's 81 photos with the 16 query-split photos' GPS removed, two San Francisco photos, a text file named
.jpg and a photo with broken EXIF. Checked after each line: the GeoJSON (RFC 7946) and the CSV cover every
photo without GPS; each confident position lies within its stated radius of the truth; the San Francisco
photos get no position; a second scan skips what is done; decisions write nothing; sidecars hold the
accepted GPS and leave the photos byte for byte; undo restores; in-file GPS leaves the pixels unchanged."""

from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import subprocess
from pathlib import Path

import pytest

from app.engine.configs import DEFAULT_CONFIG
from app.engine.geo import haversine_m
from app.library.writeback import pixel_hash
from tests.api.test_readme_commands import ACTIVATE, commands
from tests.conftest import REPO
from tests.library.conftest import ELSEWHERE, copy_collection, make_library

#: A whole library scanned with the fitted default pipeline: make test, not make test-quick.
pytestmark = pytest.mark.library

GUIDE = (REPO / "docs" / "guide.md").read_text()
SECTION = GUIDE.split("## Geolocating a photo library")[1].split("\n## ")[0]
LINES = [c for c in commands(SECTION) if c.startswith("geoloc library")]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def gps_of(path: Path) -> tuple[float, float] | None:
    out = subprocess.run(["exiftool", "-n", "-j", "-GPSLatitude", "-GPSLongitude", str(path)], capture_output=True)
    got = json.loads(out.stdout)[0]
    return (got["GPSLatitude"], got["GPSLongitude"]) if "GPSLatitude" in got else None


@pytest.fixture(scope="module")
def shell(tmp_path_factory, library_models, query_truth, penn_collection):
    home = tmp_path_factory.mktemp("library-home")
    work = home / "work"
    work.mkdir()
    make_library(home / "library", query_truth)
    # D holds the references already (the session's collection): the scan's ingest finds them present
    # ("adds them to an existing --data-dir"), the locating is the README line's own.
    copy_collection(penn_collection, work / "D")
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith(("GEOLOC_", "VIRTUAL_ENV"))},
        "HOME": str(home),
        "GEOLOC_MODELS_DIR": str(library_models),
        "GEOLOC_CONFIG": DEFAULT_CONFIG,
        "PYTHONUNBUFFERED": "1",
    }

    def run(line: str) -> subprocess.CompletedProcess:
        script = f'set -eo pipefail\ncd "{REPO}"\n{ACTIVATE}\ncd "{work}"\n{line}\n'
        p = subprocess.run(["bash", "-c", script], capture_output=True, text=True, env=env, timeout=900, cwd=work)
        assert p.returncode == 0, (line, p.stdout[-3000:], p.stderr[-3000:])
        return p

    run.home, run.work, run.library = home, work, home / "library"
    return run


def _line(start: str) -> str:
    """The one README line that is ``start`` exactly, or else the one that starts with it."""
    found = [c for c in LINES if c == start] or [c for c in LINES if c.startswith(start)]
    assert len(found) == 1, (start, LINES)
    return found[0]


def test_the_readme_library_lines(shell, query_truth):
    lib, work = shell.library, shell.work
    originals = {p.name: sha(p) for p in lib.iterdir()}
    ran = []

    # 1. The scan: every photo without GPS is one Feature and one CSV row.
    line = _line("geoloc library scan ~/library --data-dir D --geojson")
    out = shell(line).stdout
    ran.append(line)
    assert "65 references (with a position)" in out, out
    assert re.search(r"threads on \d+ usable CPUs", out), out
    assert "notes.jpg: not an image" in out, out  # a bad file is listed, the run goes on
    collection = json.loads((work / "out.geojson").read_text())
    assert collection["type"] == "FeatureCollection"
    by_name = {Path(f["properties"]["file"]).name: f for f in collection["features"]}
    # Every photo without a position: the 16, the two from elsewhere, the broken one, and the file that is
    # not an image (unplaced, its reason "unreadable").
    assert set(query_truth) | set(ELSEWHERE) | {"broken-exif.jpg", "notes.jpg"} == set(by_name), sorted(by_name)
    assert by_name["notes.jpg"]["geometry"] is None and by_name["notes.jpg"]["properties"]["reason_code"]
    rows = {Path(r["file"]).name: r for r in csv.DictReader((work / "out.csv").open())}
    assert set(rows) == set(by_name)
    placed = confident = 0
    for name, truth in query_truth.items():
        f = by_name[name]
        props = f["properties"]
        if f["geometry"] is None:
            assert props["reason_code"] and props["reason"], props
            assert rows[name]["lat"] == ""
            continue
        placed += 1
        lon, lat = f["geometry"]["coordinates"]  # RFC 7946: longitude first
        assert f["geometry"]["type"] == "Point" and -76 < lon < -75 and 39 < lat < 40
        assert props["radius_m"] > 0 and props["basis"] in ("pixels", "time", "pixels+time", "sequence")
        assert float(rows[name]["lat"]) == pytest.approx(lat) and float(rows[name]["radius_m"]) == props["radius_m"]
        if props["confident"]:
            confident += 1
            d = float(haversine_m(lat, lon, *truth))
            assert d <= props["radius_m"], (name, d, props)
    assert placed == 16 and confident >= 5, (placed, confident)  # bench/library_time_prior.py: 16 and 10
    for name in ELSEWHERE:  # San Francisco: no position, and why
        assert by_name[name]["geometry"] is None and by_name[name]["properties"]["reason_code"], by_name[name]
    assert "EXIF unreadable" in by_name["broken-exif.jpg"]["properties"]["note"], by_name["broken-exif.jpg"]
    assert {p.name: sha(p) for p in lib.iterdir()} == originals  # a scan writes nothing

    # 2. Again: nothing located twice.
    line = _line("geoloc library scan ~/library --data-dir D")
    out = shell(line).stdout
    ran.append(line)
    assert "0 located now, 19 done by an earlier run" in out, out

    for start in ("geoloc library list", "geoloc library decide"):
        for line in [c for c in LINES if c.startswith(start)]:
            shell(line)
            ran.append(line)
    listed = [json.loads(x) for x in shell(_line("geoloc library list")).stdout.splitlines()]
    decisions = {Path(p["file"]).name: p["decision"] for p in listed}
    # What each camera's run is read from (app/library/joint.py): the calibrated candidates of each photo
    # (none here: this collection, the library's 65 photos, is not the one the pipeline was calibrated on;
    # tests/library/test_joint.py scans against a calibrated one).
    for p in listed:
        assert p["calibrated_candidates"] == [] and p["basis"] != "sequence" and "alone" not in p, p
    assert decisions["img_00001.jpg"] == "accepted" and decisions["img_00008.jpg"] == "accepted"
    assert decisions["img_00009.jpg"] == "rejected"
    assert {p.name: sha(p) for p in lib.iterdir()} == originals  # a decision writes nothing

    line = _line("geoloc library write ~/library --data-dir D --dry-run")
    out = shell(line).stdout
    ran.append(line)
    assert "would write" in out and "2 would write" in out, out
    assert {p.name: sha(p) for p in lib.iterdir()} == originals

    # 3. Sidecars: the accepted GPS beside the photo, the photos byte for byte, nothing for the rejected.
    line = _line("geoloc library write ~/library --data-dir D")
    ran.append(line)
    out = shell(line).stdout
    assert "2 wrote" in out, out
    lon1, lat1 = by_name["img_00001.jpg"]["geometry"]["coordinates"]
    assert gps_of(lib / "img_00001.jpg.xmp") == pytest.approx((lat1, lon1), abs=1e-6)
    assert gps_of(lib / "img_00008.jpg.xmp") == pytest.approx((39.95041, -75.19229), abs=1e-6)
    assert not (lib / "img_00009.jpg.xmp").exists()
    assert {p.name: sha(p) for p in lib.iterdir() if p.suffix != ".xmp"} == originals
    again = shell(line).stdout  # written already: nothing to do
    assert "0 wrote" in again, again

    line = _line("geoloc library export")
    shell(line)
    ran.append(line)
    accepted = json.loads((work / "accepted.geojson").read_text())
    names = sorted(Path(f["properties"]["file"]).name for f in accepted["features"])
    assert names == ["img_00001.jpg", "img_00008.jpg"]
    gpx = (work / "accepted.gpx").read_text()
    assert gpx.count("<wpt ") == 2 and 'lat="39.95041"' in gpx

    # 4. Undo: the sidecars are gone, every file as it was.
    line = _line("geoloc library undo")
    shell(line)
    ran.append(line)
    assert {p.name: sha(p) for p in lib.iterdir()} == originals

    # 5. In the photo: EXIF GPS written, the decoded pixels unchanged.
    pixels = {n: pixel_hash(lib / n) for n in ("img_00001.jpg", "img_00008.jpg", "img_00009.jpg")}
    line = _line("geoloc library write ~/library --data-dir D --in-file")
    shell(line)
    ran.append(line)
    assert gps_of(lib / "img_00008.jpg") == pytest.approx((39.95041, -75.19229), abs=1e-6)
    assert gps_of(lib / "img_00009.jpg") is None and sha(lib / "img_00009.jpg") == originals["img_00009.jpg"]
    assert sha(lib / "img_00008.jpg") != originals["img_00008.jpg"]
    assert {n: pixel_hash(lib / n) for n in pixels} == pixels
    # A photo we wrote GPS into is still ours to review, never taken as a reference by the next scan.
    out = shell(_line("geoloc library scan ~/library --data-dir D")).stdout
    assert "65 references" in out and "0 located now, 19 done by an earlier run" in out, out
    shell(_line("geoloc library undo"))
    assert {p.name: sha(p) for p in lib.iterdir()} == originals

    assert sorted(set(ran)) == sorted(set(LINES)), set(LINES) - set(ran)
