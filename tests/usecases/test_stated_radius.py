"""A stated disc that holds: a real fit of a 20-photo penn collection (each photo with two of its crops)
calibrates every answer's disc split-conformally on its own references, per bin of evidence strength, the
places removed from the collection counting as answers no disc holds; the discs are the conformal quantiles
of the errors the calibration recorded, counted in captures (made monotone, floored); an answer states its
bin's disc and the rate when it is informative and is "possible" otherwise; a conservative collection keeps
the constant rule and says its rate is not calibrated; a calibration.json from before discs still loads.
The same fit's calibration counts its support in captures (a photo and its crops): no probability above
what its captures can show, a confident level only on the right answers of enough captures."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from app.api.schemas import LocateOut
from app.cli import estimate_in_words, radius_in_words, rate_in_words
from app.domain import LocateOptions
from app.engine.calibration import (
    MIN_DISC_BIN,
    RADIUS_RATE,
    Calibration,
    Disc,
    answer_probability,
    choose_threshold,
    fit_calibration,
    max_p,
)
from app.engine.configs import get_config
from app.engine.estimate import MARGIN_M, RADIUS_FLOOR_M, Estimate
from app.engine.geo import haversine_m
from app.engine.pipeline import Pipeline
from app.engine.training.svm_training import index_of
from app.usecases import fitting as fitting_module
from app.usecases.extraction import extract_batch
from app.usecases.fitting import FitOptions, FitPhoto, GeotaggedReferences, bank_source, fit_pipeline
from app.usecases.locate import locate_features
from tests.conftest import PENN

CONFIG = "hybrid-bin"
PHOTOS = 20


@pytest.fixture(scope="module")
def fitted(squeezenet, models_dir, penn_index):
    """The pipeline fitted on the first 20 penn captures (60 references), and the calibration's samples as
    ``fit_calibration`` received them (recorded on their way: the fit runs unchanged)."""
    captures = [r for r in penn_index if r["photo"]][:PHOTOS]
    photos = [
        FitPhoto(path=PENN / img, lat=float(r["lat"]), lon=float(r["lon"]), group=r["photo_id"])
        for r in captures
        for img in [r["photo"], *r["crops"].split(";")[:2]]
    ]
    config = get_config(CONFIG)
    pipe = Pipeline(config, global_model=squeezenet, models_dir=models_dir)
    seen = []
    real = fitting_module.fit_calibration
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fitting_module, "fit_calibration", lambda s, *a, **k: seen.append(s) or real(s, *a, **k))
        fit = fit_pipeline(pipe, photos, FitOptions(bank=bank_source(config, None), bank_optional=True))
    return fit, seen[0]


def _expected_radius(errors) -> float:
    """The conformal quantile, counted here independently: the ceil((n + 1) * 0.9)-th smallest error."""
    e = sorted(errors)
    return e[math.ceil((len(e) + 1) * RADIUS_RATE) - 1]


def test_the_discs_are_the_conformal_quantiles_of_the_recorded_errors(fitted):
    fit, samples = fitted
    cal = fit.pipeline.calibration
    assert cal.calibrated and cal.disc is not None, cal.note
    d = Disc(**cal.disc)
    assert d.rate == RADIUS_RATE and d.basis == "answer_p" and d.limit_m <= 100
    present = [s for s in samples if not s.absent]
    for s in present:  # each error is the estimate's distance from the truth, 25 m deciding "within"
        assert s.error_m >= 0 and (s.error_m <= 25) == s.estimate_within
    p = np.array([answer_probability(cal, s) for s in samples])
    err = np.array([np.inf if s.absent else s.error_m for s in samples])  # a place removed: no disc holds it
    assert d.edges == sorted(d.edges) and sum(d.n) == len(samples)
    bin_of = np.searchsorted(d.edges, p, side="right")
    assert d.n == np.bincount(bin_of, minlength=len(d.edges) + 1).tolist()
    raw = []
    for k in range(len(d.edges) + 1):
        assert (bin_of == k).sum() >= MIN_DISC_BIN
        # Counted in captures: each capture (present, or removed) once, with its worst error in the bin.
        worst = {}
        for j in np.flatnonzero(bin_of == k):
            key = (samples[j].group, samples[j].absent)
            worst[key] = max(worst.get(key, 0.0), err[j])
        n = len(worst)
        raw.append(_expected_radius(list(worst.values())) if math.ceil((n + 1) * RADIUS_RATE) <= n else np.inf)
    # Monotone (a bin never narrower than a stronger one) and floored, then rounded to 0.1 m; infinite: None.
    expected = [max(max(raw[k:]), RADIUS_FLOOR_M) for k in range(len(raw))]
    assert d.radius_m == [round(r, 1) if np.isfinite(r) else None for r in expected]
    for k, r in enumerate(d.radius_m):
        if r is not None:
            assert np.mean(err[bin_of == k] <= r + 0.05) >= RADIUS_RATE  # it holds on the sample itself
    # 20 captures: no bin holds enough of them (9 at 90 %) for an informative disc, so no answer has an
    # estimate, and the collection says what it needs.
    assert not d.informative_anywhere and "no answer can be confident" in cal.confidence_note(60), d.radius_m
    # The weakest bin holds the places removed from the collection: no disc at all.
    assert d.radius_m[0] is None
    # And the note (the fit's and refit's summary, /ready) says how discs are chosen.
    assert "; discs of " in cal.note and "each holding for 90 % of" in cal.note, cal.note


def _query(fit, penn_index):
    """A penn photo the fit never saw whose place the collection holds (a reference within 25 m)."""
    refs = fit.refs
    for r in [r for r in penn_index if r["photo"]][PHOTOS:]:
        lat, lon = float(r["lat"]), float(r["lon"])
        if any(haversine_m(lat, lon, g.lat, g.lon) <= 25 for g in refs.values()):
            return PENN / r["photo"]
    raise AssertionError("no penn photo near the collection")


def test_an_answer_states_its_disc_and_the_rate_when_it_is_informative(fitted, penn_index):
    fit, samples = fitted
    cal, pipe = fit.pipeline.calibration, fit.pipeline
    d = Disc(**cal.disc)
    # Every sampled answer: an estimate with its bin's disc and the rate when that disc is informative.
    for s in samples:
        members = tuple(bool(m) for m in s.members)
        e = Estimate(0.0, 0.0, RADIUS_FLOOR_M, 1.0, None, int(s.members.sum()), members)
        decision = cal.decide(s.evidence, e)
        r = d.estimate_radius(decision.answer_p)
        if r is None:
            assert not decision.confident and decision.code in ("ambiguous", "no_match")
            assert "not in this collection" not in decision.reason
        else:
            assert decision.confident and (decision.radius_m, decision.radius_rate) == (r, 0.9)
    # Every answer read as informative (the limit raised): through the locate path, the estimate carries the
    # disc and the rate, and /locate's JSON states it.
    anyone = replace(cal, disc={**cal.disc, "limit_m": 1e9, "radius_m": [r or 1e6 for r in d.radius_m]})
    ids = sorted(fit.refs)
    index = index_of(pipe, ids, (fit.refs[i].features for i in ids))
    source = GeotaggedReferences(fit.refs)
    features = extract_batch(pipe, [_query(fit, penn_index)])[0].features
    options = LocateOptions(top_k=10, rerank=False)
    answer = locate_features(pipe, index, source, features, options, calibration=anyone)
    assert answer.reason is None and answer.answer_p is not None
    stated = Disc(**anyone.disc).radius(answer.answer_p)
    assert (answer.estimate.radius_m, answer.estimate.radius_rate) == (stated, 0.9)
    shown = LocateOut.of(answer).model_dump()["estimate"]
    assert shown["radius_rate"] == 0.9 and shown["radius_m"] == round(answer.estimate.radius_m, 1)
    # `geoloc locate --brief` says it in the page's words.
    assert radius_in_words(shown) == f"within {shown['radius_m']:.0f} m: 9 in 10 such answers are"
    assert estimate_in_words(shown).endswith(f"m of {shown['lat']:.5f},{shown['lon']:.5f}: 9 in 10 such answers are")
    assert rate_in_words(0.95) == "19 in 20"

    # A conservative collection keeps the constant rule, and its rate is not calibrated.
    plain = locate_features(pipe, index, source, features, options, calibration=Calibration.conservative("small"))
    assert plain.estimate.radius_rate is None and plain.estimate.radius_m >= MARGIN_M


def test_a_calibration_from_before_discs_still_loads_and_keeps_the_confident_threshold(fitted, tmp_path):
    fit, samples = fitted
    cal = fit.pipeline.calibration
    cal.save(tmp_path)
    data = json.loads((tmp_path / "calibration.json").read_text())
    del data["disc"]
    (tmp_path / "calibration.json").write_text(json.dumps(data))
    old = Calibration.load(tmp_path)
    assert old.calibrated and old.disc is None and old.confident_p == cal.confident_p
    assert "fitted before discs" in old.note and "geoloc refit" in old.note
    assert radius_in_words({"radius_m": 48.0, "radius_rate": None}).endswith("is not calibrated on this collection")
    s = max(samples, key=lambda s: answer_probability(cal, s))
    e = Estimate(0.0, 0.0, 99.0, 1.0, None, int(s.members.sum()), tuple(bool(m) for m in s.members))
    d = replace(old, confident_p=0.0).decide(s.evidence, e)
    assert d.confident and d.radius_m is None and d.radius_rate is None  # locate keeps the estimate's own
    # Today's file round-trips with its discs.
    cal.save(tmp_path)
    assert Calibration.load(tmp_path).disc == cal.disc


def test_the_calibration_counts_its_support_in_captures(fitted):
    """Each photo's crops answer like the photo, so the calibration's 60 references are 20 observations: its
    probabilities never exceed what 20 right captures could show (``max_p``); the same answers of 8 captures
    (24 references, enough to calibrate) state at most ``max_p(8)``, and their threshold is the
    one the regression's own probabilities give wherever it lies below the ceiling."""
    fit, samples = fitted
    cal = fit.pipeline.calibration
    present = [s for s in samples if not s.absent]
    captures = {s.group for s in present}
    assert None not in captures and len(captures) == PHOTOS < len(present)  # 3 references per capture
    assert cal.report["captures"] == PHOTOS and cal.ceiling == pytest.approx(max_p(PHOTOS)) and cal.ceiling < 0.93
    assert max(float(cal.probabilities(s.evidence).max()) for s in samples) <= cal.ceiling
    eight = sorted(captures)[:8]
    small = fit_calibration([s for s in samples if s.group in eight])
    assert small.calibrated and small.report["captures"] == 8 and small.ceiling == pytest.approx(max_p(8))
    top = max(float(small.probabilities(s.evidence).max()) for s in samples)
    uncapped = replace(small, ceiling=1.0)
    # The regression's own probability, capped at the ceiling (which binds where it lies below).
    own = max(float(uncapped.probabilities(s.evidence).max()) for s in samples)
    assert top == pytest.approx(min(own, small.ceiling)) and top <= small.ceiling
    if choose_threshold(uncapped, [s for s in samples if s.group in eight]) < small.ceiling:
        assert small.confident_p == choose_threshold(uncapped, [s for s in samples if s.group in eight])


def test_a_calibration_from_before_the_ceiling_still_loads_and_states_its_regression(fitted, tmp_path):
    fit, samples = fitted
    cal = fit.pipeline.calibration
    cal.save(tmp_path)
    data = json.loads((tmp_path / "calibration.json").read_text())
    del data["ceiling"]
    (tmp_path / "calibration.json").write_text(json.dumps(data))
    old = Calibration.load(tmp_path)
    assert old.ceiling == 1.0
    top = max(samples, key=lambda s: answer_probability(cal, s))
    assert old.probabilities(top.evidence).max() >= cal.probabilities(top.evidence).max()
    cal.save(tmp_path)
    assert Calibration.load(tmp_path).ceiling == cal.ceiling


def test_the_calibration_leaves_out_every_reference_taken_at_the_same_spot(fitted):
    """A manifest without groups names each crop its own group: the calibration still leaves out every
    reference taken at the located one's spot, so a crop is never located against its own photo (0 m off,
    which stated 10 m discs that held for a third of real queries)."""
    fit, _ = fitted
    refs = {i: replace(g, group=f"row{i}") for i, g in fit.refs.items()}  # every reference its own group
    seen = []
    real = fitting_module.fit_calibration
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fitting_module, "fit_calibration", lambda s, *a, **k: seen.append(s) or real(s, *a, **k))
        fitting_module.calibrate_collection(fit.pipeline, refs)
    present = [s for s in seen[0] if not s.absent]
    assert len(present) >= 50 and min(s.error_m for s in present) > 0.1, sorted(s.error_m for s in present)[:5]
