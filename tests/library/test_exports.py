"""Exports of a library's journal: GeoJSON as RFC 7946 says (lon, lat; null geometry with its reason), CSV,
GPX by gpxpy; the accepted positions only unless everything is asked for."""

from __future__ import annotations

import csv
import io
import json

import gpxpy

from app.library.exports import render
from app.library.review import decide
from app.storage.library import LOCATED, LibraryJournal


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
