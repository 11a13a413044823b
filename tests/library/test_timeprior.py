"""The time prior's rules on the real photos' metadata (penn's EXIF times, cameras and offsets)."""

from __future__ import annotations

from datetime import timedelta

from app.library.photos import parse_exif_time, read_meta
from app.library.timeprior import FLOOR_M, SPEED_M_S, Anchor, time_only_radius, time_prior
from tests.conftest import PENN, SHARED


def test_penn_photos_state_their_time_offset_and_camera():
    m = read_meta(PENN / "photos" / "img_00000.jpg")
    assert m.camera == "samsung SM-A315F" and m.gps is not None
    assert m.taken is not None and m.taken.utcoffset() == timedelta(hours=-4)
    sf = read_meta(SHARED / "data" / "sf-streetview-toy" / "queries" / "q1.jpg")
    assert sf.taken is None and sf.gps is None and sf.problem is None


def test_the_prior_prefers_the_same_camera_and_grows_with_the_gap():
    t = parse_exif_time("2024:09:23 16:10:00-04:00")
    anchors = [
        Anchor(39.950, -75.190, parse_exif_time("2024:09:23 16:10:20-04:00"), "Apple iPhone 13"),
        Anchor(39.952, -75.192, parse_exif_time("2024:09:23 16:09:00-04:00"), "samsung SM-A315F"),
    ]
    p = time_prior(t, "samsung SM-A315F", anchors)
    assert (p.lat, p.lon, p.same_camera, p.gap_s) == (39.952, -75.192, True, 60.0)
    assert p.radius_m == FLOOR_M + SPEED_M_S * 60 and time_only_radius(p) == p.radius_m
    other = time_prior(t, "Pixel 7", anchors)  # no photo of its camera: the nearest of all, never "time only"
    assert other.gap_s == 20.0 and not other.same_camera and time_only_radius(other) is None
    assert time_prior(t + timedelta(hours=1), None, anchors) is None  # nothing within the window
    assert time_prior(None, None, anchors) is None
    naive = parse_exif_time("2024:09:23 16:10:00")  # no offset: never compared with a zoned time
    assert naive.tzinfo is None and time_prior(naive, None, anchors) is None
    assert parse_exif_time("0000:00:00 00:00:00") is None
