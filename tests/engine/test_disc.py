"""The disc every answer states (``app.engine.calibration.fit_disc``), on synthetic samples whose truth is
known: split-conformal per bin of evidence strength, it holds the truth for about the stated rate of new
answers drawn alike (overall and for the weakest evidence), stronger evidence never states a wider disc, no
disc is narrower than the floor, places removed from the collection get none, too few answers give none;
and the rule built on it (``Calibration.decide``) gives an estimate only where the disc is informative,
in words that claim only what was measured, and survives a save and load."""

import json

import numpy as np

from app.engine.calibration import (
    AMBIGUOUS,
    MAX_EXTENT_SHARE,
    MIN_DISC_BIN,
    NO_MATCH,
    Calibration,
    Disc,
    Sample,
    disc_bin_captures,
    disc_reason,
    fit_calibration,
    fit_disc,
)
from app.engine.estimate import RADIUS_FLOOR_M, fuse_position
from app.engine.evidence import gather
from app.engine.geo import haversine_m
from tests.engine.test_calibration import LAT0, LON0, _answer


def _draw(rng, n: int):
    """Answers whose error grows as the evidence weakens (an exponential of scale 15 m at strength 1, 150 m
    at 0); some places absent (error infinite), the more the weaker the evidence (half of them at 0)."""
    s = rng.uniform(0, 1, n)
    err = rng.exponential(15 + 135 * (1 - s))
    absent = rng.uniform(0, 1, n) < 0.5 * (1 - s) ** 3
    err[absent] = np.inf
    return s, err


def _coverage(disc: Disc, s, err):
    r = np.array([disc.radius(x) if disc.radius(x) is not None else np.nan for x in s])
    stated = ~np.isnan(r)
    return stated, err[stated] <= r[stated]


def test_the_disc_holds_for_about_the_rate_on_answers_it_was_not_fitted_on():
    rng = np.random.default_rng(0)
    disc = fit_disc(*_draw(rng, 3000), rate=0.9)
    assert disc is not None and disc.rate == 0.9 and len(disc.radius_m) > 10
    assert all(n >= MIN_DISC_BIN for n in disc.n) and sum(disc.n) == 3000
    s, err = _draw(np.random.default_rng(1), 20000)
    stated, held = _coverage(disc, s, err)
    assert 0.5 < stated.mean() < 1.0  # the weakest bins, mostly absent places, state none
    assert 0.88 <= held.mean() <= 0.96, held.mean()
    weakest = np.argsort(s[stated])[: stated.sum() // 4]
    assert held[weakest].mean() >= 0.85, held[weakest].mean()
    # At another rate: wider discs, holding more often.
    wide = fit_disc(*_draw(np.random.default_rng(0), 3000), rate=0.95)
    _, held95 = _coverage(wide, s, err)
    assert held95.mean() > held.mean() and held95.mean() >= 0.93


def test_stronger_evidence_never_states_a_wider_disc_and_absent_places_get_none():
    rng = np.random.default_rng(2)
    disc = fit_disc(*_draw(rng, 2000))
    radii = [np.inf if r is None else r for r in disc.radius_m]
    assert radii == sorted(radii, reverse=True), radii  # from the weakest bin to the strongest
    assert disc.radius_m[0] is None and disc.radius_m[-1] is not None  # the weak bins hold absent places
    # A stronger bin wider than its weaker neighbour is pooled with it and refitted: one unlucky strong bin
    # (11 of its 100 captures far off) spends its failures on the captures beside it, where the running
    # maximum would have left every weaker bin with no disc.
    s = np.repeat([0.1, 0.5, 0.9], 100)
    err = np.concatenate([np.full(100, 60.0), np.full(100, 20.0), np.full(89, 10.0), np.full(11, np.inf)])
    d = fit_disc(s, err, min_captures=100, min_n=100)
    assert d.edges == [0.5] and d.n == [100, 200] and d.radius_m == [60.0, 20.0]
    # Pooled until monotone: here into one bin.
    err = np.concatenate([np.full(100, 30.0), np.full(100, 20.0), np.full(100, 40.0)])
    d = fit_disc(s, err, min_captures=100, min_n=100)
    assert d.edges == [] and d.n == [300] and d.radius_m == [40.0]


def test_bins_close_at_enough_captures_from_the_strongest_down():
    """A bin closes once it holds ``min_captures`` captures and ``min_n`` answers, counted from the strongest
    answer down; ties stay together and the weak remainder joins the last bin."""
    s = np.linspace(1, 0, 100)
    groups = [k // 2 for k in range(100)]  # 50 captures of two answers each
    d = fit_disc(s, np.full(100, 15.0), groups, min_captures=20, min_n=25)
    # From the strongest: 39 answers reach 20 captures, the next 39 again, the last 22 join that second bin.
    assert d.n == [61, 39] and d.edges == [s[38]] and d.radius_m == [15.0, 15.0]
    tied = np.repeat([0.9, 0.2], 50)
    assert fit_disc(tied, np.full(100, 15.0), min_captures=20, min_n=25).n == [50, 50]
    # By default a bin holds the fewest captures whose quantile survives one far off: 19 at 90 %.
    assert [disc_bin_captures(r) for r in (0.8, 0.9, 0.95)] == [9, 19, 39]
    one_off = np.where(np.arange(100) == 0, 500.0, 15.0)  # the strongest capture 500 m off
    d = fit_disc(s, one_off, groups)
    assert d.n == [63, 37] and d.radius_m == [15.0, 15.0]  # 19 captures in 37 answers: the 18th of 19 holds


def test_a_bin_counts_its_captures_once_with_their_worst_error():
    """Answers of one capture (a photo and its crops) fail together: counted in captures, a bin of 30
    answers from 10 captures, one of whose three answers lies 80 m off, states 80 m (the worst of each
    capture, the 10th of 10 at 90 %), where counted one by one it stated 5 m; from 6 captures, none."""
    s = np.full(30, 0.9)
    err = np.full(30, 5.0)
    err[0] = 80.0
    groups = [k // 3 for k in range(30)]
    assert fit_disc(s, err, rate=0.9).radius_m == [RADIUS_FLOOR_M]
    assert fit_disc(s, err, groups, rate=0.9).radius_m == [80.0]
    assert fit_disc(s, err, [k // 5 for k in range(30)], rate=0.9).radius_m == [None]


def test_no_disc_is_narrower_than_the_floor():
    rng = np.random.default_rng(3)
    s = rng.uniform(0, 1, 500)
    d = fit_disc(s, rng.uniform(0, 2, 500))  # every answer within 2 m
    assert d.radius_m == [RADIUS_FLOOR_M] * len(d.radius_m)
    assert fit_disc(s, rng.uniform(0, 2, 500), floor_m=5.0).radius_m[0] == 5.0


def test_too_few_answers_give_no_disc():
    rng = np.random.default_rng(4)
    assert fit_disc(*_draw(rng, MIN_DISC_BIN - 1)) is None
    assert fit_disc(*_draw(rng, MIN_DISC_BIN)) is not None  # one bin


def test_an_estimate_only_where_the_disc_is_informative():
    d = Disc(rate=0.9, edges=[0.3, 0.6], radius_m=[None, 150.0, 40.0], n=[30, 30, 30], limit_m=100.0, max_radius_m=100)
    assert d.radius(0.1) is None and d.radius(0.5) == 150.0 and d.radius(0.9) == 40.0
    assert d.estimate_radius(0.1) is None and d.estimate_radius(0.5) is None and d.estimate_radius(0.9) == 40.0
    # The limit: the maximum radius, or a share of the collection's extent when that is smaller.
    rng = np.random.default_rng(5)
    s, err = _draw(rng, 1000)
    assert fit_disc(s, err, max_radius_m=80).limit_m == 80
    assert fit_disc(s, err, max_radius_m=80, extent_m=200).limit_m == MAX_EXTENT_SHARE * 200


def _sample(rng, present: bool) -> Sample:
    lats, lons, scores = _answer(rng, present)
    e = fuse_position(lats, lons, scores)
    error = float(haversine_m(LAT0, LON0, e.lat, e.lon))
    within = haversine_m(LAT0, LON0, lats, lons) <= 25
    return Sample(gather(lats, lons, scores), within, np.array(e.members, bool), error <= 25, not present, error)


def _decide(cal: Calibration, rng, present: bool):
    lats, lons, scores = _answer(rng, present)
    return cal.decide(gather(lats, lons, scores), fuse_position(lats, lons, scores))


def test_the_rule_states_the_disc_and_its_rate_and_says_what_it_measured(tmp_path):
    rng = np.random.default_rng(0)
    samples = [_sample(rng, present) for present in [True] * 80 + [False] * 80]
    cal = fit_calibration(samples, rate=0.9, max_radius_m=100, extent_m=2000)
    assert cal.disc is not None and cal.radius is None, cal.note
    disc = Disc(**cal.disc)
    assert disc.rate == 0.9 and disc.limit_m == 100 and disc.extent_m == 2000
    assert "discs of" in cal.note and "an estimate for those within 100 m" in cal.note
    present = [_decide(cal, rng, True) for _ in range(30)]
    assert sum(d.confident for d in present) >= 25
    for d in present:
        if d.confident:
            assert d.radius_m == disc.estimate_radius(d.answer_p) and d.radius_rate == 0.9
    absent = [_decide(cal, rng, False) for _ in range(30)]
    assert not any(d.confident for d in absent)
    assert all(d.code == NO_MATCH for d in absent)
    assert absent[0].reason.startswith("no reference looks like this photo") and "collection" not in absent[0].reason
    # Where no disc is informative: possible only, saying why (a disc too wide, or none holding at the rate).
    narrow = fit_calibration(samples, rate=0.9, max_radius_m=5, extent_m=2000)
    d = _decide(narrow, np.random.default_rng(1), True)
    assert not d.confident and d.code == AMBIGUOUS
    assert "9 in 10 such answers" in d.reason and "wider than the 5 m an estimate may state" in d.reason, d.reason
    assert narrow.confidence_note(600) is not None  # no answer of it can have an estimate: it says so
    assert disc.radius(0.0) is None and disc_reason(disc, 0.0) == (
        "no disc holds 9 in 10 such answers (evidence strength 0%): of this collection's own answers this weak, "
        "more than 1 in 10 were of places removed from it, or far off"
    )
    assert cal.confidence_note(600) is None
    # Saved with the pipeline, read back unchanged; a file from before discs says so and keeps the old rule.
    cal.save(tmp_path)
    back = Calibration.load(tmp_path)
    assert back.disc == cal.disc
    d0, d1 = _decide(cal, np.random.default_rng(7), True), _decide(back, np.random.default_rng(7), True)
    assert (d0.confident, d0.radius_m, d0.radius_rate) == (d1.confident, d1.radius_m, d1.radius_rate)
    data = json.loads((tmp_path / "calibration.json").read_text())
    del data["disc"]
    (tmp_path / "calibration.json").write_text(json.dumps(data))
    old = Calibration.load(tmp_path)
    assert old.disc is None and "fitted before discs" in old.note and "geoloc refit" in old.note


def test_a_sample_too_small_for_a_disc_keeps_the_confident_threshold():
    rng = np.random.default_rng(1)
    cal = fit_calibration([_sample(rng, p) for p in [True] * 16 + [False] * 8])
    assert cal.calibrated and cal.disc is None, cal.note  # 24 answers: too few for a disc
    small = fit_calibration([_sample(rng, p) for p in [True] * 5 + [False] * 5])
    assert not small.calibrated and "too small to calibrate" in small.note
