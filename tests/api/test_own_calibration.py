"""A collection is judged by its own calibration or by none: a data dir that reads the models
dir's pipeline, calibrated on another collection, answers with the conservative rule and says why; a refit
calibrates it on itself; a collection too small for a confident answer says what it needs, in the refit's
summary and on /ready. Real `geoloc fit`, `ingest`, `locate` and `refit` on penn photos, and a real server."""

from __future__ import annotations

import json
import shutil

import pytest

from app.engine.calibration import CONFIDENT_FROM_REFERENCES
from app.manifests import read_manifest
from app.usecases.service import GeolocService
from tests.api.conftest import CONFIG, Server
from tests.conftest import PENN
from tests.test_cli import geoloc


@pytest.fixture(scope="module")
def calibrated(forty_fitted):
    """A models dir whose hybrid-bin pipeline is fitted and calibrated by `geoloc fit` on 40 penn captures
    (120 photos and crops), with GEOLOC_MAX_RADIUS_M=90 (the run's shared fit); and that manifest."""
    models, manifest, _ = forty_fitted
    cal = json.loads((models / "pipelines" / CONFIG / "calibration.json").read_text())
    assert cal["source"] == "collection" and len(cal["references"]) == 120, cal["note"]
    assert cal["disc"]["max_radius_m"] == 90 and cal["disc"]["limit_m"] <= 90, cal["disc"]
    return models, manifest


@pytest.fixture(scope="module")
def ingested(tmp_path_factory, calibrated):
    """The calibrated manifest's 120 photos and crops ingested by `geoloc ingest` once for the module (the
    collection the pipeline was calibrated on). Each test works on its own copy (``_copy``)."""
    models, manifest = calibrated
    data = tmp_path_factory.mktemp("ingested") / "data"
    where = ["--models-dir", str(models), "--config", CONFIG]
    geoloc("ingest", "--manifest", str(manifest), "--split", "db", "--data-dir", str(data), *where)
    return data


def _copy(ingested, dest):
    shutil.copytree(ingested, dest, symlinks=True)
    return dest


def _locate(photo, data, models, *extra) -> str:
    args = ["locate", str(photo), "--data-dir", str(data), "--models-dir", str(models), "--config", CONFIG]
    return geoloc(*args, *extra).stdout


def test_a_new_collection_is_judged_by_its_own_calibration_or_by_none(tmp_path, calibrated, ingested, penn_index):
    models, _ = calibrated
    photos = tmp_path / "photos"
    photos.mkdir()
    captures = [r for r in penn_index if r["photo"]][41:61]  # 20 photos the fit never saw
    for r in captures:
        shutil.copyfile(PENN / r["photo"], photos / r["photo"].split("/")[-1])
    own, mine = _copy(ingested, tmp_path / "own"), tmp_path / "mine"
    where = ["--models-dir", str(models), "--config", CONFIG]
    geoloc("ingest", str(photos), "--data-dir", str(mine), *where)
    query = PENN / captures[3]["crops"].split(";")[0]  # a crop of a photo of `mine`: its best match is 0 m off
    # The collection the pipeline was calibrated on is judged by it: probabilities.
    answer = json.loads(_locate(query, own, models))
    assert answer["candidates"][0]["p_within_25m"] is not None
    # Another collection is not: no probability borrowed, and the words say why and what to do.
    answer = json.loads(_locate(query, mine, models))
    assert all(c["p_within_25m"] is None for c in answer["candidates"])
    assert "fitted on another collection" in answer["reason"] and "geoloc refit" in answer["reason"]
    assert "calibration was fitted on another collection" in _locate(query, mine, models, "--brief")
    service = GeolocService.open(mine, models, CONFIG)
    try:  # what /ready says of it
        assert "fitted on another collection" in service.collection.calibration_summary()
    finally:
        service.store.close()

    # A refit calibrates it on itself; 20 photos are too few for a confident answer, and both the refit's
    # summary and /ready say what it needs.
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("GEOLOC_RADIUS_RATE", "0.8")  # the discs' rate, read by the refit
        out = geoloc("refit", "--data-dir", str(mine), *where).stdout
    needs = f"no answer can be confident in this collection yet: it needs about {CONFIDENT_FROM_REFERENCES} references"
    assert needs in out and "(it has 20)" in out, out
    refitted = json.loads(next(mine.glob("pipelines/*-g1/calibration.json")).read_text())
    assert refitted["disc"]["rate"] == 0.8, refitted
    with Server(mine, models) as s:
        ready = s.client.get("/ready").json()
    assert needs in ready["calibration"], ready
    assert "fitted on another collection" not in ready["calibration"]


def test_a_refit_counts_a_photo_and_its_crops_as_one_capture(tmp_path, calibrated, ingested):
    """Penn photos carry an EXIF time and their crops none; a refit groups references by position alone, so
    a photo and its crops are one capture and the calibration never locates a crop against the photo it was
    cut from (a crop found its own photo and the rule learnt confidence from it). The refit trains no bank:
    this test reads the calibration alone."""
    models, _ = calibrated
    data = _copy(ingested, tmp_path / "forty")
    where = ["--models-dir", str(models), "--config", CONFIG]
    service = GeolocService.open(data, models, CONFIG)
    try:
        rows = service.store.get_many(service.store.indexed_ids().tolist()).values()
    finally:
        service.store.close()
    timed = {(r.lat, r.lon) for r in rows if r.captured_at}
    assert len(timed) > 0 and any(r.captured_at is None and (r.lat, r.lon) in timed for r in rows)
    geoloc("refit", "--data-dir", str(data), "--svm-bank", "none", *where)
    cal = json.loads(next(data.glob("pipelines/*-g1/calibration.json")).read_text())
    assert cal["source"] == "collection", cal["note"]
    positions = {(r.lat, r.lon) for r in rows}  # 40 captures, a few of them taken at one spot
    assert cal["report"]["captures"] == len(positions) <= 40


def test_an_answer_states_its_disc_and_its_rate_and_says_it_in_words(tmp_path, calibrated, ingested):
    """The disc every answer states, through a real server reading the persisted calibration: this
    40-capture collection's strongest disc (about 90 m) is wider than its limit (a quarter of its extent), so
    no answer has an estimate and none claims the place is absent; the same pipeline with that limit raised
    in its calibration.json states the disc: ``radius_m`` (the persisted bin's) and ``radius_rate`` (0.9), and
    `geoloc locate --brief` says "Taken within R m of ...: 9 in 10 such answers are"."""
    models, manifest = calibrated
    disc = json.loads((models / "pipelines" / CONFIG / "calibration.json").read_text())["disc"]
    assert disc is not None and disc["rate"] == 0.9 and disc["limit_m"] <= 90, disc
    own = _copy(ingested, tmp_path / "own")
    photos = [r.image for r in read_manifest(manifest)][::3][:6]  # each capture's photo, a reference itself

    def answers(models_dir):
        out = {}
        with Server(own, models_dir) as s:
            for photo in photos:
                r = s.client.post("/locate", files=[("image", (photo.name, photo.read_bytes(), "image/jpeg"))])
                assert r.status_code == 200, r.text
                out[photo] = r.json()
        return out

    informative = [r for r in disc["radius_m"] if r is not None and r <= disc["limit_m"]]
    assert not informative, disc  # this collection's own limit keeps every disc from counting
    for a in answers(models).values():
        assert a["estimate"] is None and a["reason_code"] in ("ambiguous", "no_match")
        assert "not in this collection" not in a["reason"]

    # The same pipeline, its persisted disc's limit raised: the server states the disc it reads.
    wide = tmp_path / "models"
    shutil.copytree(models, wide, symlinks=True)
    path = wide / "pipelines" / CONFIG / "calibration.json"
    data = json.loads(path.read_text())
    data["disc"]["limit_m"] = 1000.0
    path.write_text(json.dumps(data))
    estimated = {p: a for p, a in answers(wide).items() if a["estimate"] is not None}
    assert estimated
    for a in estimated.values():
        e = a["estimate"]
        assert e["radius_rate"] == 0.9 and e["radius_m"] in disc["radius_m"], e
        assert a["reason"] is None and a["reason_code"] is None
    photo, a = next(iter(estimated.items()))
    brief = _locate(photo, own, wide, "--brief")
    e = a["estimate"]
    assert brief.startswith(f"Taken within {e['radius_m']:.0f} m of ") and ": 9 in 10 such answers are" in brief, brief
