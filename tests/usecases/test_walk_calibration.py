"""The sequence's own disc: the collection's references arranged as walks (real penn times and positions),
the times read on one clock, and the disc a real calibration fits on its held-out walks."""

from __future__ import annotations

import json

import numpy as np

from app.engine.calibration import CALIBRATION_FILE, Disc
from app.engine.geo import haversine_m
from app.engine.sequence import SLACK_M, Motion
from app.engine.training.svm_training import Geotagged
from app.usecases.walk_calibration import MIN_WALK, WALK_WINDOW, capture_seconds, walk_windows
from bench.sequence_walks import walks
from tests.conftest import PENN
from tests.walks import CONFIG


def penn_walk_refs():
    """Every penn photo with a time as a reference (its capture its group), its time on the collection's one
    clock (``capture_seconds`` of the EXIF times), and its camera."""
    refs, taken, camera = {}, {}, {}
    for cam, photos in walks(PENN).items():
        for r, _, iso in photos:
            i = len(refs)
            refs[i] = Geotagged(None, float(r["lat"]), float(r["lon"]), r["photo_id"])
            taken[i], camera[i] = iso, cam
    times = capture_seconds(taken)
    assert len(times) == len(refs)
    return refs, times, camera


def test_capture_times_are_read_on_one_clock():
    secs = capture_seconds(
        {
            1: "2024-09-23T16:10:00-04:00",
            2: "2024:09:23 16:10:30",  # EXIF's form, without a zone: the first zone given
            3: "2024-09-23T20:11:00Z",
            4: "not a time",
            5: "2024-09-23",  # a date alone places no photo in a walk
        }
    )
    assert secs == {1: 0.0, 2: 30.0, 3: 60.0}
    assert capture_seconds({1: "2024-09-23T16:10:00", 2: "2024-09-23T16:09:00"}) == {1: 60.0, 2: 0.0}
    assert capture_seconds({}) == {}


def test_the_penn_photos_form_walks_that_the_motion_model_allows():
    """Three phones' photos interleave in time; chained by motion alone, each window steps within the bound
    and holds each capture once. Most windows are one phone's; the others join phones whose photographers
    walked within the bound of each other, which a walk the motion model allows cannot tell apart."""
    refs, times, camera = penn_walk_refs()
    windows = walk_windows(sorted(refs), refs, times)
    seen = [i for w in windows for i in w]
    assert len(seen) == len(set(seen)) and len(seen) >= 0.9 * len(refs)
    motion = Motion()
    for w in windows:
        assert MIN_WALK <= len(w) <= WALK_WINDOW
        for a, b in zip(w, w[1:], strict=False):
            assert times[b] >= times[a]
            d = haversine_m(refs[a].lat, refs[a].lon, refs[b].lat, refs[b].lon)
            assert d <= motion.allowed_m(times[b] - times[a]) + SLACK_M
    one_phone = sum(len({camera[i] for i in w}) == 1 for w in windows)
    assert one_phone >= 0.6 * len(windows), (one_phone, len(windows))


def test_references_without_a_time_form_no_walk_and_a_capture_counts_once():
    refs, times, _ = penn_walk_refs()
    timed = dict(list(times.items())[:10])
    crop = max(refs) + 1
    refs[crop] = Geotagged(None, refs[3].lat, refs[3].lon, refs[3].group)  # a crop of capture 3, same time
    timed[crop] = timed[3]
    windows = walk_windows(sorted(refs), refs, timed)
    seen = [i for w in windows for i in w]
    assert windows and set(seen) <= set(timed) and crop not in seen and 3 in seen


def test_the_calibration_fits_the_sequence_disc_on_its_held_out_walks(walk_built):
    """`geoloc fit` on the walk collection (its photos' EXIF times): the report says how many walks and
    photos the disc was fitted on, and the disc, where there is one, is read per posterior like the single
    disc, its rate the collection's."""
    data = json.loads((walk_built / "models" / "pipelines" / CONFIG / CALIBRATION_FILE).read_text())
    report = data["report"]["sequence"]
    assert report["window"] == WALK_WINDOW and report["walks"] >= 3
    assert MIN_WALK * report["walks"] <= report["photos"] <= WALK_WINDOW * report["walks"]
    assert 0 <= report["confident_alone"] < report["photos"]
    assert f"{report['walks']} held-out walks ({report['photos']} photos)" in data["note"]  # what fit says
    if data["sequence_disc"] is not None:
        disc = Disc(**data["sequence_disc"])
        assert disc.basis == "sequence_p" and disc.rate == data["disc"]["rate"]
        radii = [np.inf if r is None else r for r in disc.radius_m]
        assert radii == sorted(radii, reverse=True)  # stronger posteriors never state wider discs
    else:
        assert report.get("disc") == "too few walk photos for a disc"
