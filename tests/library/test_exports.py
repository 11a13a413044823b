"""Exports of a library's journal: GeoJSON as RFC 7946 says (lon, lat; null geometry with its reason), CSV,
GPX by gpxpy; the accepted positions only unless everything is asked for."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET

import gpxpy

from app.library.exports import CSV_COLUMNS, FORMATS, render, write_export
from app.library.review import decide
from app.storage.library import ACCEPTED, LOCATED, PROBLEM, LibraryJournal, PhotoRecord


def _journal(tmp_path):
    j = LibraryJournal(tmp_path)
    sid = j.start_scan(tmp_path, 2)
    placed = {"file": "/x/a.jpg", "placed": True, "confident": True, "lat": 39.95, "lon": -75.19, "radius_m": 30.0,
              "p": 0.9, "basis": "pixels", "reason_code": None, "reason": None, "candidates": []}  # fmt: skip
    none = {"file": "/x/<b>.jpg", "placed": False, "confident": False, "lat": None, "lon": None, "radius_m": None,
            "p": 0.1, "basis": None, "reason_code": "no_match", "reason": "no match", "candidates": []}  # fmt: skip
    j.record(sid, tmp_path / "a.jpg", 1, 1, LOCATED, placed)
    j.record(sid, tmp_path / "b.jpg", 1, 1, LOCATED, none)
    return j, sid


def test_geojson_csv_gpx(tmp_path):
    j, sid = _journal(tmp_path)
    doc = json.loads(render(j.photos(sid), "geojson", True))
    assert doc["type"] == "FeatureCollection" and len(doc["features"]) == 2
    a, b = doc["features"]
    assert a["geometry"] == {"type": "Point", "coordinates": [-75.19, 39.95]}  # longitude first
    assert a["properties"]["radius_m"] == 30.0 and a["properties"]["basis"] == "pixels"
    assert b["geometry"] is None and b["properties"]["reason_code"] == "no_match" and b["properties"]["reason"]
    rows = list(csv.DictReader(io.StringIO(render(j.photos(sid), "csv", True))))
    assert [r["lat"] for r in rows] == ["39.95", ""] and rows[1]["reason_code"] == "no_match"
    gpx = gpxpy.parse(render(j.photos(sid), "gpx", True))
    assert [(w.latitude, w.longitude) for w in gpx.waypoints] == [(39.95, -75.19)]  # GPX cannot say "nowhere"

    assert json.loads(render(j.photos(sid), "geojson", False))["features"] == []  # nothing accepted yet
    a_id = j.photos(sid)[0].id
    decide(j, sid, a_id, "move", 39.951, -75.191)
    moved = json.loads(render(j.photos(sid), "geojson", False))["features"]
    assert [f["geometry"]["coordinates"] for f in moved] == [[-75.191, 39.951]]
    assert moved[0]["properties"]["basis"] == "user" and moved[0]["properties"]["radius_m"] is None
    j.close()


def test_csv_cells_never_run_as_formulas_and_all_includes_unreadable_files(tmp_path):
    j = LibraryJournal(tmp_path)
    sid = j.start_scan(tmp_path, 2)
    placed = {"file": "/x/=a.jpg", "placed": True, "confident": True, "lat": 39.95, "lon": -75.19,
              "radius_m": 30.0, "p": 0.9, "basis": "pixels", "camera": '=HYPERLINK("http://x","y")',
              "candidates": []}  # fmt: skip
    j.record(sid, tmp_path / "=a.jpg", 1, 1, LOCATED, placed)
    j.record(sid, tmp_path / "-notes.jpg", 1, 1, PROBLEM, {"file": "x", "reason": "not an image"})
    rows = list(csv.DictReader(io.StringIO(render(j.photos(sid), "csv", True))))
    by_name = {r["file"].rsplit("/", 1)[-1]: r for r in rows}
    assert by_name["=a.jpg"]["camera"] == '\'=HYPERLINK("http://x","y")' and by_name["=a.jpg"]["lon"] == "-75.19"
    for row in rows:
        assert not any(v.startswith(("=", "+", "-", "@", "\t", "\r")) for k, v in row.items() if k != "lon"), row
    doc = json.loads(render(j.photos(sid), "geojson", True))
    unreadable = [f for f in doc["features"] if f["properties"]["reason_code"] == "unreadable"]
    assert len(unreadable) == 1 and unreadable[0]["geometry"] is None
    assert unreadable[0]["properties"]["reason"] == "not an image"
    assert len(json.loads(render(j.photos(sid), "geojson", False))["features"]) == 0  # accepted only: none
    j.close()


def test_exports_are_utf8_whatever_the_locale(tmp_path):
    out = tmp_path / "out.csv"
    code = (
        "import sys; from pathlib import Path; from app.library.exports import write_export;"
        "from app.storage.library import LOCATED, PROBLEM, LibraryJournal;"
        "t = Path(sys.argv[1]); j = LibraryJournal(t);"
        "s = j.start_scan(t, 1);"
        "j.record(s, t / 'caf\\u00e9.jpg', 1, 1, LOCATED, {'placed': False, 'reason': 'no match', 'candidates': []});"
        "write_export(j.photos(s), 'csv', True, t / 'out.csv')"
    )
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    p = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    assert "café.jpg" in out.read_bytes().decode("utf-8")


# Every character XML 1.0 forbids (C0 controls but tab, newline and carriage return; U+FFFE, U+FFFF; lone
# surrogates, which a str can hold though no UTF-8 file can), plus a bare carriage return and a newline.
FORBIDDEN = "".join(map(chr, [*range(0x00, 0x09), 0x0B, 0x0C, *range(0x0E, 0x20)])) + "\ufffe\uffff"
SURROGATES = "\ud800\udfff"


def _record(rid: int, path: str, decision: str | None) -> PhotoRecord:
    result = {"file": path, "placed": True, "confident": True, "lat": 39.95, "lon": -75.19, "radius_m": 30.0,
              "p": 0.9, "basis": "pixels\x1b", "camera": "cam\x07" + SURROGATES, "candidates": []}  # fmt: skip
    return PhotoRecord(rid, "s", path, 1, 1, LOCATED, result, decision, 39.95 if decision else None,
                       -75.19 if decision else None, None)  # fmt: skip


def test_every_export_is_well_formed_whatever_characters_a_file_name_holds(tmp_path):
    name = "a\x1bb" + FORBIDDEN + "\r\n\rc" + SURROGATES + "\U0001f600<&>é.jpg"
    records = [_record(1, "/x/" + name, ACCEPTED), _record(2, "/x/plain.jpg", None)]
    readable = re.sub("[\ud800-\udfff]", "\ufffd", name)  # what a UTF-8 file can hold of the name
    for everything in (True, False):
        gpx_xml = render(records, "gpx", everything)
        root = ET.fromstring(gpx_xml.encode("utf-8"))  # a str with lone surrogates cannot even be encoded
        names = [w.text for w in root.iter("{http://www.topografix.com/GPX/1/1}name")]
        assert names == [re.sub("[\x00-\x08\x0b\x0c\x0e-\x1f\ufffe\uffff\ud800-\udfff]", "\ufffd", name)] + (
            ["plain.jpg"] if everything else []
        )
        assert [w.name for w in gpxpy.parse(gpx_xml).waypoints] == names

        doc = json.loads(render(records, "geojson", everything).encode("utf-8"))
        assert doc["features"][0]["properties"]["file"] == "/x/" + readable

        table = list(csv.reader(io.StringIO(render(records, "csv", everything).encode("utf-8").decode("utf-8"),
                                            newline="")))  # fmt: skip
        assert len(table) == 2 + everything and table[1][0] == "/x/" + readable, table
        assert table[1][CSV_COLUMNS.index("camera")] == "cam\x07\ufffd\ufffd"

    for fmt in FORMATS:  # the files as written hold the same
        out = tmp_path / f"out.{fmt}"
        assert write_export(records, fmt, True, out) == 2
        out.read_bytes().decode("utf-8")
    assert gpxpy.parse((tmp_path / "out.gpx").read_text(encoding="utf-8")).waypoints[0].name.startswith("a\ufffdb")
    with (tmp_path / "out.csv").open(encoding="utf-8", newline="") as f:
        assert next(r for r in csv.DictReader(f) if r["file"] != "/x/plain.jpg")["file"] == "/x/" + readable
