"""The sequence use case on real photos: a held-out penn walk, the 22 San Francisco images, times."""

from __future__ import annotations

from datetime import datetime

import pytest

from app.domain import LocateOptions
from app.engine.calibration import Disc
from app.engine.sequence import Motion
from app.errors import InvalidRequest
from app.usecases.sequence import PIXELS, SEQUENCE, locate_sequence, sequence_answers
from app.usecases.sequence_inputs import seconds, sequence_times, taken_order
from app.usecases.service import GeolocService
from tests.conftest import PENN
from tests.walks import CONFIG

ELSEWHERE = sorted((PENN.parent / "sf-streetview-toy").glob("*/*.jpg"))


@pytest.fixture(scope="module")
def service(walk_collection):
    models, data, _ = walk_collection
    return GeolocService.open(data, models, CONFIG)


def test_the_walk_answers_each_photo_and_a_confident_one_rests_on_its_pixels(service, walk_collection):
    _, _, walk = walk_collection
    result = locate_sequence(service, [p.read_bytes for p in walk], LocateOptions(top_k=5), Motion())
    assert result.times_from == "exif" and result.note is None
    assert len(result.photos) == len(result.path) == len(walk)
    for photo in result.photos:
        alone = photo.alone
        assert len(alone.candidates) >= 10  # located with every candidate the model reads
        assert len(photo.answer.candidates) <= 5  # shown as asked
        assert photo.sequence_p is None or 0 <= photo.sequence_p <= 1
        if alone.reason is None:  # confident alone: kept as it is
            assert photo.rests_on == PIXELS and photo.answer.estimate == alone.estimate
        if photo.rests_on == SEQUENCE:  # by the collection's walk disc (fitted on its photos' EXIF times)
            fitted = service.answer_calibration(LocateOptions()).sequence_disc
            assert fitted is not None, "an answer rests on the sequence, but the collection has no walk disc"
            walks = Disc(**fitted)
            assert photo.answer.reason is None and walks.estimate_radius(photo.sequence_p) is not None


def test_a_sequence_of_one_photo_is_the_photo_alone(service, walk_collection):
    """Only what the sequence adds reorders: one photo keeps its own ranking and its own answer."""
    options = LocateOptions(top_k=10)
    calibration = service.answer_calibration(options)
    for photo in walk_collection[2][:3]:
        alone = service.locate(photo.read_bytes(), options)
        (one,) = sequence_answers([alone], [None], calibration, Motion(), options).photos
        assert [c.reference_id for c in one.answer.candidates] == [c.reference_id for c in alone.candidates]
        assert (one.answer.reason is None) == (alone.reason is None) or one.rests_on == SEQUENCE


#: Three orders of the 22 San Francisco images. In the interleaved one, neighbours' candidates happen to
#: agree more often; with steps of 500 m every place of the walk collection is in reach of every other, so
#: continuity is worth nothing there (``Motion.continuity_gain``) and no order lifts a photo to an estimate.
ELSEWHERE_ORDERS = [
    pytest.param(list(range(22)), id="in-order"),
    pytest.param(list(range(21, -1, -1)), id="reversed"),
    pytest.param([*range(0, 22, 2), *range(1, 22, 2)], id="interleaved"),
]


@pytest.fixture(scope="module")
def elsewhere(service):
    return [service.locate(p.read_bytes(), LocateOptions(top_k=10)) for p in ELSEWHERE]


@pytest.mark.parametrize("order", ELSEWHERE_ORDERS)
def test_a_sequence_from_elsewhere_gets_no_estimate(service, elsewhere, order):
    options = LocateOptions()
    calibration = service.answer_calibration(options)
    assert calibration.calibrated and Disc(**calibration.disc).informative_anywhere  # an estimate is possible here
    result = sequence_answers([elsewhere[i] for i in order], [None] * 22, calibration, Motion(step_m=500), options)
    assert all(p.answer.reason is not None for p in result.photos)
    assert not any(q.in_collection for q in result.path)  # the path stays out of this collection


def test_times_given_exif_or_order():
    walk = [PENN / "photos" / f"img_0000{n}.jpg" for n in (3, 4, 5)]
    readers = [p.read_bytes for p in walk]
    secs, source = sequence_times(readers, None)
    assert source == "exif" and secs[0] == 0 and secs[1] == 6 and secs[2] == 136
    secs, source = sequence_times(readers, ["2024-09-23T16:00:00", "2024-09-23 16:00:30", "2024-09-23T16:01:00Z"])
    assert source == "given" and secs == [0, 30, 60]  # the naive ones read in the sequence's one zone
    with pytest.raises(InvalidRequest, match="go backwards: image 1"):
        sequence_times(readers[::-1][:2], None)
    with pytest.raises(InvalidRequest, match="date without a time"):
        sequence_times(readers, ["2024-09-23", "2024-09-23", "2024-09-23"])
    assert seconds([datetime(2024, 1, 1), None]) == [None, None]
    secs, source = sequence_times([lambda: b"not an image", lambda: b""], None)
    assert source == "order" and secs == [None, None]
    # Photos in any order: their times, unchecked, and the order they were taken in.
    secs, source = sequence_times(readers[::-1], None, in_order=False)
    assert source == "exif" and secs == [0, -130, -136]
    assert taken_order(secs) == ([2, 1, 0], [0, 6, 136])
    assert taken_order([0.0, -5.0, 0.0]) == ([1, 0, 2], [0, 5, 5])  # a burst keeps the order given
    assert taken_order([None, None, None]) == ([0, 1, 2], [None, None, None])


def test_a_sequence_estimate_takes_the_single_photo_rules_disc_and_claims_no_rate():
    """The disc rule decides and sizes a sequence's estimate; its rate, measured on single photos only, is
    not claimed for it."""
    import numpy as np

    from app.engine.calibration import Calibration
    from app.engine.sequence import Places
    from app.usecases.sequence import sequence_estimate

    calibration = Calibration(
        source="collection",
        disc={"rate": 0.9, "edges": [0.75], "radius_m": [None, 35.0], "n": [50, 50], "limit_m": 80.0,
              "max_radius_m": 100.0},
    )  # fmt: skip
    places = Places(np.array([39.952, 39.960]), np.array([-75.193, -75.190]), np.zeros(3), np.array([5.0, 0.0]))
    e = sequence_estimate(places, np.array([0.8, 0.15, 0.05]), calibration)
    assert (e.lat, e.lon, e.radius_m, e.radius_rate) == (39.952, -75.193, 45.0, None)  # the place's spread + 40 m
    assert sequence_estimate(places, np.array([0.7, 0.25, 0.05]), calibration) is None  # no disc that weak
    assert sequence_estimate(places, np.array([0.1, 0.05, 0.85]), calibration) is None  # not in the collection


def check_walk_answers(result, disc: Disc) -> None:
    """A photo confident alone keeps its own answer; every other estimate is the walk disc's at its
    posterior, with its rate, resting on the sequence; every photo without one reads a posterior the disc
    does not inform, and says why."""
    for photo in result.photos:
        e, alone, p = photo.answer.estimate, photo.alone, photo.sequence_p
        if alone.reason is None:
            assert photo.rests_on == PIXELS and e == alone.estimate and photo.answer.reason is None
        elif photo.answer.reason is None:
            assert disc.estimate_radius(p) is not None and e.radius_rate == disc.rate
            assert e.radius_m >= disc.estimate_radius(p) and photo.rests_on == SEQUENCE
        else:
            assert disc.estimate_radius(p) is None and photo.rests_on == PIXELS
            assert "with the sequence" in photo.answer.reason


def test_the_walk_disc_states_the_sequence_s_estimates_and_their_rate(service, walk_collection):
    """A collection calibrated on its own walks (`geoloc fit` read the photos' EXIF times) answers each photo
    not confident alone by the sequence's disc, at its rate. With a disc that informs half of the walk's
    posteriors, those of them not confident alone get it."""
    from dataclasses import replace

    from app.usecases.sequence import single_options
    from app.usecases.sequence_inputs import exif_time

    _, _, walk = walk_collection
    options = LocateOptions(top_k=5)
    calibration = service.answer_calibration(options)
    assert calibration.sequence_disc is not None and calibration.sequence_disc["basis"] == "sequence_p"
    singles = [service.locate(p.read_bytes(), single_options(options)) for p in walk]
    times = seconds([exif_time(p.read_bytes()) for p in walk])
    served = sequence_answers(singles, times, calibration, Motion(), options)
    check_walk_answers(served, Disc(**calibration.sequence_disc))
    posteriors = sorted(p.sequence_p for p in served.photos if p.alone.reason is not None)
    middle = posteriors[len(posteriors) // 2]
    disc = {**calibration.sequence_disc, "edges": [middle], "radius_m": [None, 60.0], "n": [25, 25], "limit_m": 80.0}
    informed = sequence_answers(singles, times, replace(calibration, sequence_disc=disc), Motion(), options)
    check_walk_answers(informed, Disc(**disc))
    by_walks = [p for p in informed.photos if p.rests_on == SEQUENCE]
    assert len(by_walks) == sum(p >= middle for p in posteriors) > 0
    assert all(p.answer.estimate.radius_rate == calibration.sequence_disc["rate"] for p in by_walks)
