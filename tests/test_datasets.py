"""Manifests: the penn-campus-gps split keeps captures together and puts crop-only captures in db."""

import pytest

from app.evaluation.datasets import penn_campus_rows
from app.manifests import ManifestError, read_manifest, write_manifest
from tests.conftest import PENN


def test_penn_split_by_capture(tmp_path):
    rows = penn_campus_rows(PENN, seed=0)
    assert len(rows) == 81 + 500
    sides = {}
    for r in rows:
        sides.setdefault(r.group, set()).add(r.split)
    assert all(len(s) == 1 for s in sides.values())  # a photo and its crops share a side
    groups_with_photo = {r.group for r in rows if "/photos/" in str(r.image)}
    crop_only = set(sides) - groups_with_photo
    assert len(crop_only) == 19 and all(sides[g] == {"db"} for g in crop_only)
    counts = {s: sum(1 for g in groups_with_photo if sides[g] == {s}) for s in ("db", "query", "train")}
    assert counts == {"db": 49, "query": 16, "train": 16}
    assert penn_campus_rows(PENN, seed=0) == rows  # seeded
    assert penn_campus_rows(PENN, seed=1) != rows


def test_round_trip_with_relative_paths(tmp_path):
    rows = penn_campus_rows(PENN)[:12]
    path = tmp_path / "sub" / "m.csv"
    write_manifest(path, rows)
    assert "shared" in path.read_text() and not path.read_text().split("\n")[1].startswith("/")
    back = read_manifest(path)
    assert [(r.image, r.split, r.group) for r in back] == [(r.image, r.split, r.group) for r in rows]


@pytest.mark.parametrize(
    "body, message",
    [
        ("image,lat\nx.jpg,1\n", "missing columns"),
        ("image,lat,lon,split\nx.jpg,91,0,db\n", "out of range"),
        ("image,lat,lon,split\nx.jpg,abc,0,db\n", "not numbers"),
        ("image,lat,lon,split\nx.jpg,1,1,test\n", "split"),
    ],
)
def test_bad_manifests_say_what_is_wrong(tmp_path, body, message):
    p = tmp_path / "bad.csv"
    p.write_text(body)
    with pytest.raises(ManifestError, match=message):
        read_manifest(p)
