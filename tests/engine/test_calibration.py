"""The confidence rule and p_within_25m (app.engine.calibration) on evidence gathered the way locate gathers
it (app.engine.evidence): fitted on present and absent answers, it says "no_match" for an absent place,
is confident for a clear present one, round-trips through the pipeline folder, and a sample too small to
calibrate falls back to the conservative rule with no probabilities."""

from dataclasses import asdict

import numpy as np

from app.engine.calibration import AMBIGUOUS, NO_MATCH, Calibration, Sample, fit_calibration
from app.engine.estimate import fuse_position
from app.engine.evidence import GLOBAL_NAMES, VERIFIED_NAMES, gather
from app.engine.geo import haversine_m
from app.engine.matchers.base import Verification

LAT0, LON0 = 39.952, -75.193


def _offset(dx_m: float, dy_m: float):
    return LAT0 + dy_m / 111_320, LON0 + dx_m / (111_320 * np.cos(np.radians(LAT0)))


def _answer(rng, present: bool):
    """Ten candidates best first: a present place has a few right ones agreeing near the truth (0, 0) with
    a score lead; an absent one has look-alikes scattered 150-800 m away with flat scores."""
    n_right = int(rng.integers(2, 5)) if present else 0
    pts, scores = [], []
    for k in range(10):
        if k < n_right:
            pts.append(_offset(*rng.uniform(-8, 8, 2)))
            scores.append(0.72 - 0.01 * k + rng.normal(0, 0.01))
        else:
            r, a = rng.uniform(150, 800), rng.uniform(0, 2 * np.pi)
            pts.append(_offset(r * np.cos(a), r * np.sin(a)))
            scores.append(0.60 - 0.004 * k + rng.normal(0, 0.01))
    order = np.argsort(-np.array(scores))
    lats, lons = np.array(pts)[order].T
    return lats, lons, np.array(scores)[order]


def _sample(rng, present: bool) -> Sample:
    lats, lons, scores = _answer(rng, present)
    e = fuse_position(lats, lons, scores)
    within = haversine_m(LAT0, LON0, lats, lons) <= 25
    return Sample(
        gather(lats, lons, scores),
        within,
        np.array(e.members, bool),
        bool(haversine_m(LAT0, LON0, e.lat, e.lon) <= 25),
        absent=not present,
    )


def _decide(cal: Calibration, rng, present: bool):
    lats, lons, scores = _answer(rng, present)
    return cal.decide(gather(lats, lons, scores), fuse_position(lats, lons, scores))


def test_absent_places_get_no_match_and_present_ones_a_confident_answer(tmp_path):
    rng = np.random.default_rng(0)
    cal = fit_calibration([_sample(rng, present) for present in [True] * 60 + [False] * 60])
    assert cal.calibrated and cal.names == GLOBAL_NAMES and 0 < cal.confident_p <= 1
    absent = [_decide(cal, rng, False) for _ in range(30)]
    assert all(not d.confident and d.code == NO_MATCH and d.p_within.max() < 0.1 for d in absent)
    assert absent[0].reason.startswith("no reference looks like this photo")
    present = [_decide(cal, rng, True) for _ in range(30)]
    assert sum(d.confident for d in present) >= 25
    assert all(d.p_within[0] > 0.5 for d in present)
    # The rule is stored with the pipeline and read back unchanged.
    cal.save(tmp_path)
    back = Calibration.load(tmp_path)
    d0, d1 = _decide(cal, np.random.default_rng(5), True), _decide(back, np.random.default_rng(5), True)
    assert back.names == cal.names and np.allclose(d0.p_within, d1.p_within) and d0.confident == d1.confident


def test_a_collection_too_small_to_calibrate_says_so_and_gives_no_probabilities(tmp_path):
    rng = np.random.default_rng(1)
    cal = fit_calibration([_sample(rng, p) for p in [True] * 5 + [False] * 5])
    assert not cal.calibrated and "too small to calibrate" in cal.note
    strong = _decide(cal, np.random.default_rng(2), True)
    lats, lons, scores = _answer(np.random.default_rng(3), False)
    weak = cal.decide(gather(lats, lons, scores), fuse_position(lats, lons, scores))
    assert strong.p_within is None and weak.p_within is None
    assert not weak.confident and weak.code == AMBIGUOUS and "too small to calibrate" in weak.reason
    # A pipeline folder from before calibration existed: the same conservative rule, never another's figures.
    assert not Calibration.load(tmp_path / "old").calibrated


def test_verification_evidence_is_more_columns_of_the_same_vector():
    lats, lons, scores = _answer(np.random.default_rng(4), True)
    ids = list(range(100, 110))
    verified = {100: Verification(80, 40, "F", mean_confidence=0.75), 101: None, 102: Verification(10, 0, None)}
    ev = gather(lats, lons, scores, verified, ids)
    assert ev.names == GLOBAL_NAMES + VERIFIED_NAMES and ev.verified
    row = dict(zip(ev.names, ev.values[0], strict=True))
    assert row["log_inliers"] == np.log1p(40) and row["inlier_ratio"] == 0.5
    assert row["match_confidence"] == 0.75  # a learned matcher's mean match probability is read, not lost
    assert ev.values[1, len(GLOBAL_NAMES) :].tolist() == [0, 0, 0, 0]  # unverifiable: reads as no evidence
    # A rule fitted without verification reads only its own columns from verified evidence.
    plain = gather(lats, lons, scores)
    assert np.array_equal(ev.columns(GLOBAL_NAMES), plain.values)


def test_distinctiveness_reads_score_differences_against_other_places():
    """lead_over_far: a candidate's score above the best candidate more than 100 m from it (the rival place);
    with no rival among the candidates, above the last one. Shifting every score leaves both columns as
    they are (a new photo's absolute score level is not evidence)."""
    here, near, far = _offset(0, 0), _offset(10, 0), _offset(400, 0)
    lats = np.array([here[0], near[0], far[0]])
    lons = np.array([here[1], near[1], far[1]])
    scores = np.array([0.70, 0.66, 0.61])
    ev = gather(lats, lons, scores)
    lead = ev.values[:, ev.names.index("lead_over_far")]
    assert np.allclose(lead, [0.70 - 0.61, 0.66 - 0.61, 0.61 - 0.70])
    assert ev.values[0, ev.names.index("gap_1_last")] == np.float64(0.70) - np.float64(0.61)
    lone = gather(lats[:2], lons[:2], scores[:2])  # no rival place: the lead over the last candidate
    assert np.allclose(lone.values[:, lone.names.index("lead_over_far")], [0.70 - 0.66, 0.0])
    shifted = gather(lats, lons, scores + 0.05)
    for name in ("lead_over_far", "gap_1_last"):
        j = ev.names.index(name)
        assert np.allclose(shifted.values[:, j], ev.values[:, j])


def test_calibration_parts_are_whole_captures_bounded_by_the_sample():
    """The references the calibration locates: whole captures, each in one part (an auxiliary fit leaves a
    part out, so a photo's crops are never fitted on while it is located), at most ``sample`` of them."""
    from app.engine.training.svm_training import Geotagged
    from app.usecases.fitting import HOLDOUT_PARTS, calibration_parts

    refs = {i: Geotagged(None, LAT0, LON0, f"g{i // 3}") for i in range(60)}  # 20 captures of 3
    parts = calibration_parts(refs, sample=600, seed=0)
    assert len(parts) == HOLDOUT_PARTS and sorted(sum(parts, [])) == list(range(60))
    for p in parts:
        groups = {refs[i].group for i in p}
        assert all(refs[j].group not in groups for q in parts if q is not p for j in q)
    small = calibration_parts(refs, sample=20, seed=0)
    assert sum(len(p) for p in small) == 20 and len(small) < HOLDOUT_PARTS
    assert calibration_parts(refs, sample=600, seed=1) != parts  # seeded


def test_a_match_above_anything_the_calibration_saw_is_never_not_in_this_collection():
    """Evidence is read within the calibration sample's range; a best score above it (a reference's own
    photo: the sample never holds a duplicate) is ambiguous at worst, never no_match."""
    rng = np.random.default_rng(0)
    cal = fit_calibration([_sample(rng, present) for present in [True] * 60 + [False] * 60])
    lats, lons, scores = _answer(np.random.default_rng(9), False)
    scores = scores.copy()
    scores[0] = 1.0  # the photo itself, among look-alikes elsewhere
    d = cal.decide(gather(lats, lons, scores), fuse_position(lats, lons, scores))
    assert d.code != NO_MATCH and np.all((d.p_within >= 0) & (d.p_within <= 1))
    assert d.confident or "above anything this collection's calibration saw" in d.reason
    # The same look-alikes without the photo itself: no reference looks like this photo.
    lats, lons, scores = _answer(np.random.default_rng(9), False)
    assert cal.decide(gather(lats, lons, scores), fuse_position(lats, lons, scores)).code == NO_MATCH


def test_a_verified_answer_is_judged_by_the_verified_rule_which_survives_a_restart(tmp_path):
    rng = np.random.default_rng(7)
    plain, verified = [], []
    for k in range(40):
        right = k % 2 == 0
        lats, lons, scores = _answer(rng, right)
        ids = list(range(10))
        # Verification that says what the truth is: many inliers for the right place, none elsewhere.
        outcome = {i: Verification(100, 60 if right and i < 3 else 0, "F" if right and i < 3 else None) for i in ids}
        within = np.zeros(10, bool)
        within[:3] = right
        members = np.zeros(10, bool)
        members[:3] = True
        plain.append(Sample(gather(lats, lons, scores), within, members, right, False))
        verified.append(Sample(gather(lats, lons, scores, outcome, ids), within, members, right, False))
    cal = fit_calibration(plain)
    cal.verified = asdict(fit_calibration(verified))
    assert cal.for_answer(False) is cal
    rule = cal.for_answer(True)
    assert rule.names == GLOBAL_NAMES + VERIFIED_NAMES and rule.calibrated
    cal.save(tmp_path)
    back = Calibration.load(tmp_path)
    assert back.for_answer(True).names == rule.names and back.for_answer(True).coef == rule.coef
    assert back.verified["names"] == cal.verified["names"]  # a tuple again, as it was saved
    # Without a verified rule a verified answer reads the plain rule's global columns.
    assert fit_calibration(plain).for_answer(True).names == GLOBAL_NAMES


def test_an_ambiguous_reason_does_not_repeat_its_code():
    """The page once showed "ambiguous: ambiguous: ..." (the code, then words that began with it)."""
    rng = np.random.default_rng(0)
    cal = fit_calibration([_sample(rng, present) for present in [True] * 60 + [False] * 60])
    cal.confident_p = 0.9999  # nothing is confident: the present places are ambiguous
    d = _decide(cal, rng, True)
    assert d.code == AMBIGUOUS and not d.reason.lower().startswith("ambiguous"), d.reason
    assert "chance of lying within 25 m" in d.reason


def test_a_calibration_judges_only_the_collection_it_was_fitted_on():
    rng = np.random.default_rng(0)
    cal = fit_calibration([_sample(rng, present) for present in [True] * 60 + [False] * 60])
    cal.references = [f"{i:064x}" for i in range(40)]
    assert cal.for_collection(40) is cal and cal.for_collection(20) is cal  # its own (a few deleted)
    other = cal.for_collection(3)
    assert not other.calibrated and "fitted on another collection (3 of the 40" in other.note
    cal.references = []  # fitted before calibrations recorded their references
    assert not cal.for_collection(40).calibrated
    assert cal.confidence_note(120) is None
    cal.confident_p = 1.01  # never confident
    assert "it needs about" in cal.confidence_note(20) and "(it has 20)" in cal.confidence_note(20)
