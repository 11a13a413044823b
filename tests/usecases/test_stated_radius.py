"""A stated radius that holds (issue 32): a real fit of a 20-photo penn collection (each photo with two of
its crops) calibrates each confident answer's radius split-conformally on its own references, per bin of
evidence strength; the radii are the conformal quantiles of the errors the calibration recorded, a
confident answer states its bin's radius and the rate, a conservative collection keeps the constant rule
and says its rate is not calibrated, and a calibration.json from before stated radii still loads. The
same fit's calibration counts its support in captures (a photo and its crops, issue 32): no probability
above what its captures can show, a confident level only on the right answers of enough captures."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from app.api.schemas import LocateOut
from app.cli import radius_in_words, rate_in_words
from app.domain import LocateOptions
from app.engine import calibration as calibration_module
from app.engine.calibration import (
    MIN_BIN_SAMPLES,
    RADIUS_BINS,
    RADIUS_RATE,
    Calibration,
    answer_probability,
    choose_threshold,
    fit_calibration,
    fit_radius,
    max_p,
)
from app.engine.configs import get_config
from app.engine.estimate import MARGIN_M, RADIUS_FLOOR_M, Estimate
from app.engine.geo import haversine_m
from app.engine.pipeline import Pipeline
from app.engine.training.svm_training import index_of
from app.usecases.extraction import extract_batch
from app.usecases.fitting import FitOptions, FitPhoto, GeotaggedReferences, bank_source, fit_pipeline
from app.usecases.locate import locate_features
from tests.conftest import PENN

CONFIG = "hybrid-bin"
PHOTOS = 20


@pytest.fixture(scope="module")
def fitted(squeezenet, models_dir, penn_index):
    """The pipeline fitted on the first 20 penn captures (60 references), and the calibration's samples as
    ``fit_radius`` received them (recorded on their way: the fit runs unchanged)."""
    captures = [r for r in penn_index if r["photo"]][:PHOTOS]
    photos = [
        FitPhoto(path=PENN / img, lat=float(r["lat"]), lon=float(r["lon"]), group=r["photo_id"])
        for r in captures
        for img in [r["photo"], *r["crops"].split(";")[:2]]
    ]
    config = get_config(CONFIG)
    pipe = Pipeline(config, global_model=squeezenet, models_dir=models_dir)
    seen = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(calibration_module, "fit_radius", lambda cal, s: seen.append(s) or fit_radius(cal, s))
        fit = fit_pipeline(pipe, photos, FitOptions(bank=bank_source(config, None), bank_optional=True))
    return fit, seen[0]


def _expected_radius(errors) -> float:
    """The conformal quantile, counted here independently: the ceil((n + 1) * 0.9)-th smallest error."""
    e = sorted(errors)
    return e[math.ceil((len(e) + 1) * RADIUS_RATE) - 1]


def test_the_radii_are_the_conformal_quantiles_of_the_recorded_errors(fitted):
    fit, samples = fitted
    cal = fit.pipeline.calibration
    assert cal.calibrated and cal.radius is not None, cal.note
    r = cal.radius
    assert r["rate"] == RADIUS_RATE and r["basis"] == "answer_p"
    present = [s for s in samples if not s.absent]
    assert len(present) >= MIN_BIN_SAMPLES
    for s in present:  # each error is the estimate's distance from the truth, 25 m deciding "within"
        assert s.error_m >= 0 and (s.error_m <= 25) == s.estimate_within
    p = np.array([answer_probability(cal, s) for s in present])
    err = np.array([s.error_m for s in present])
    confident = p >= cal.confident_p
    if r["population"] == "confident":
        assert confident.sum() >= MIN_BIN_SAMPLES
        p, err = p[confident], err[confident]
    else:  # too few confident answers to fit on: every present one (wider errors, a wider radius)
        assert r["population"] == "present" and confident.sum() < MIN_BIN_SAMPLES
    assert len(r["edges"]) < RADIUS_BINS and r["edges"] == sorted(r["edges"])
    assert len(r["edges"]) >= min(len(p) // MIN_BIN_SAMPLES, RADIUS_BINS) - 1  # merged only on ties
    bin_of = np.searchsorted(r["edges"], p, side="right")
    assert r["n"] == np.bincount(bin_of, minlength=len(r["edges"]) + 1).tolist()
    for k, radius in enumerate(r["radius_m"]):
        errors = err[bin_of == k]
        assert len(errors) >= MIN_BIN_SAMPLES
        assert radius == round(_expected_radius(errors), 1)
        assert np.mean(errors <= radius + 0.05) >= RADIUS_RATE  # it holds on the sample itself
    # The weakest bin's errors are the larger: its radius is not the strongest's.
    assert r["radius_m"][0] >= r["radius_m"][-1]
    # And the note (the fit's and refit's summary, /ready) says how radii are chosen.
    assert "; stated radii " in cal.note and "each holding for 90 % of" in cal.note, cal.note


def _query(fit, penn_index):
    """A penn photo the fit never saw whose place the collection holds (a reference within 25 m)."""
    refs = fit.refs
    for r in [r for r in penn_index if r["photo"]][PHOTOS:]:
        lat, lon = float(r["lat"]), float(r["lon"])
        if any(haversine_m(lat, lon, g.lat, g.lon) <= 25 for g in refs.values()):
            return PENN / r["photo"]
    raise AssertionError("no penn photo near the collection")


def test_a_confident_answer_states_its_bins_radius_and_the_rate(fitted, penn_index):
    fit, samples = fitted
    cal, pipe = fit.pipeline.calibration, fit.pipeline
    # Every sampled answer, judged as confident (the threshold set below it): its bin's radius and the rate.
    lowest = min(answer_probability(cal, s) for s in samples)
    anyone = replace(cal, confident_p=lowest)
    r = cal.radius
    for s in samples:
        members = tuple(bool(m) for m in s.members)
        e = Estimate(0.0, 0.0, RADIUS_FLOOR_M, 1.0, None, int(s.members.sum()), members)
        d = anyone.decide(s.evidence, e)
        k = int(np.searchsorted(r["edges"], d.answer_p, side="right"))
        assert d.confident and d.radius_m == max(r["radius_m"][k], RADIUS_FLOOR_M) and d.radius_rate == 0.9
        # Never below the constant rule's radius for the same answer (the sample is easier than real queries).
        wide = replace(e, radius_m=max(r["radius_m"]) + 50.0)
        assert anyone.decide(s.evidence, wide).radius_m == wide.radius_m

    # Through the locate path: the estimate carries the radius and the rate, and /locate's JSON states it.
    ids = sorted(fit.refs)
    index = index_of(pipe, ids, (fit.refs[i].features for i in ids))
    source = GeotaggedReferences(fit.refs)
    features = extract_batch(pipe, [_query(fit, penn_index)])[0].features
    options = LocateOptions(top_k=10, rerank=False)
    answer = locate_features(pipe, index, source, features, options, calibration=anyone)
    assert answer.reason is None and answer.answer_p is not None
    plain = locate_features(pipe, index, source, features, options, calibration=Calibration.conservative("small"))
    constant = plain.estimate.radius_m  # the same fused estimate, its radius by the constant rule
    stated = anyone.stated_radius(answer.answer_p, constant)
    assert (answer.estimate.radius_m, answer.estimate.radius_rate) == stated and stated[0] >= constant
    shown = LocateOut.of(answer).model_dump()["estimate"]
    assert shown["radius_rate"] == 0.9 and shown["radius_m"] == round(answer.estimate.radius_m, 1)
    # `geoloc locate --brief` says it in the page's words.
    assert radius_in_words(shown) == f"within {shown['radius_m']:.0f} m: 9 in 10 such answers are"
    assert rate_in_words(0.95) == "19 in 20"

    # A conservative collection keeps the constant rule, and its rate is not calibrated.
    assert plain.estimate.radius_rate is None and plain.estimate.radius_m >= MARGIN_M


def test_a_calibration_from_before_stated_radii_still_loads_and_keeps_the_constant_rule(fitted, tmp_path):
    fit, samples = fitted
    cal = fit.pipeline.calibration
    cal.save(tmp_path)
    data = json.loads((tmp_path / "calibration.json").read_text())
    del data["radius"]
    (tmp_path / "calibration.json").write_text(json.dumps(data))
    old = Calibration.load(tmp_path)
    assert old.calibrated and old.radius is None and old.confident_p == cal.confident_p
    assert "fitted before stated radii" in old.note and "geoloc refit" in old.note
    assert old.stated_radius(0.99) == (None, None)
    assert "not calibrated" in old.radius_note
    assert radius_in_words({"radius_m": 48.0, "radius_rate": None}).endswith("is not calibrated on this collection")
    s = max(samples, key=lambda s: answer_probability(cal, s))
    e = Estimate(0.0, 0.0, 99.0, 1.0, None, int(s.members.sum()), tuple(bool(m) for m in s.members))
    d = replace(old, confident_p=0.0).decide(s.evidence, e)
    assert d.confident and d.radius_m is None and d.radius_rate is None  # locate keeps the estimate's own
    # Today's file round-trips with its radii.
    cal.save(tmp_path)
    assert Calibration.load(tmp_path).radius == cal.radius


def test_the_calibration_counts_its_support_in_captures(fitted):
    """Each photo's crops answer like the photo, so the calibration's 60 references are 20 observations: its
    probabilities never exceed what 20 right captures could show (``max_p``); the same answers of 8 captures
    (24 references, enough to calibrate) state at most ``max_p(8)``, which binds, and their threshold is the
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
    assert top == pytest.approx(small.ceiling)
    uncapped = replace(small, ceiling=1.0)
    assert max(float(uncapped.probabilities(s.evidence).max()) for s in samples) > small.ceiling
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
