"""One core for every face: /locate, `geoloc locate` and the function the evaluation calls give the same
answer; the estimate does not depend on top_k; eval runs the core's rerank and region; operations."""

import json
import sqlite3
import subprocess
import sys

import numpy as np
import pytest

from app.api.schemas import LocateOut
from app.domain import LocateOptions
from app.engine.configs import get_config
from app.engine.imageio import load_image
from app.engine.pipeline import load_pipeline
from app.storage.store import ReferenceStore
from app.usecases.collection import index_from_stream
from app.usecases.locate import StoreReferences, locate_features
from tests.api.conftest import CONFIG, Server
from tests.conftest import PENN
from tests.test_cli import geoloc


@pytest.fixture
def ingested(mini_collection):
    return mini_collection


def test_every_face_gives_the_same_answer(ingested, fitted_models):
    photo = PENN / "photos" / "img_00001.jpg"  # a query capture of the mini manifest: not in the collection
    cli = json.loads(
        geoloc(
            "locate", str(photo), "--top-k", "5", "--data-dir", str(ingested), "--models-dir", str(fitted_models)
        ).stdout
    )
    with Server(ingested, fitted_models) as s:
        r = s.client.post("/locate", files=[("image", ("q.jpg", photo.read_bytes(), "image/jpeg"))], data={"top_k": 5})
        api = r.json()
    pipe = load_pipeline(fitted_models, CONFIG)
    store = ReferenceStore(ingested)
    with store.code_stream() as stream:
        index = index_from_stream(pipe, stream.chunks)
    features = pipe.extract(pipe.decode(photo.read_bytes()).rgb)  # as the service decodes
    core = LocateOut.of(
        locate_features(pipe, index, StoreReferences(store), features, LocateOptions(top_k=5))
    ).model_dump()
    for other in (cli, api):
        assert [c["reference_id"] for c in other["candidates"]] == [c["reference_id"] for c in core["candidates"]]
        assert [c["score"] for c in other["candidates"]] == pytest.approx(
            [c["score"] for c in core["candidates"]], abs=1e-6
        )
        assert other["reason"] == core["reason"]
        assert (other["estimate"] is None) == (core["estimate"] is None)
        if core["estimate"]:
            assert other["estimate"] == pytest.approx(core["estimate"], abs=1e-6)
    assert len(core["candidates"]) == 5 and core["index"]["size"] == 0  # the bare function knows no data dir
    assert api["index"]["size"] == 30 == cli["index"]["size"]
    # The tests' pipeline is fitted without calibration: the conservative rule gives no probabilities, and
    # says why (tests/api/test_answers.py has a calibrated collection).
    assert all(c["p_within_25m"] is None for c in api["candidates"])
    assert api["reason_code"] in (None, "ambiguous") and api["index"]["extent"] is not None


def test_the_estimate_does_not_depend_on_top_k(ingested, fitted_models):
    pipe = load_pipeline(fitted_models, CONFIG)
    store = ReferenceStore(ingested)
    with store.code_stream() as stream:
        index = index_from_stream(pipe, stream.chunks)
    refs = StoreReferences(store)
    for name in ("img_00001.jpg", "img_00006.jpg", "img_00011.jpg"):
        features = pipe.extract(load_image((PENN / "photos" / name).read_bytes()).rgb)
        answers = [locate_features(pipe, index, refs, features, LocateOptions(top_k=k)) for k in (1, 3, 10, 20)]
        assert [len(a.candidates) for a in answers] == [1, 3, 10, 20]
        for a in answers[1:]:
            assert (a.estimate.lat, a.estimate.lon, a.estimate.confidence, a.reason) == (
                answers[0].estimate.lat,
                answers[0].estimate.lon,
                answers[0].estimate.confidence,
                answers[0].reason,
            )
        high = locate_features(pipe, index, refs, features, LocateOptions(top_k=10, min_score=0.999))
        assert high.candidates == [] and high.estimate == answers[0].estimate  # min_score only filters the list


def test_eval_with_rerank_and_region(fitted_models, mini_manifest, tmp_path):
    out = tmp_path / "eval.json"
    p = geoloc(
        "eval", "--manifest", str(mini_manifest), "--config", CONFIG, "--models-dir", str(fitted_models),
        "--rerank", "--region-radius-m", "150", "--json", str(out),
    )  # fmt: skip
    assert "rerank" in p.stdout and "region 150 m" in p.stdout
    r = json.loads(out.read_text())
    assert r["rerank"] is True and r["region_radius_m"] == 150 and "rerank" in r["ms_per_query"]
    assert r["n_query"] == 9 and 0 <= r["recall_at"]["1"] <= 1
    # One run reports recall with and without verification (the search is the same) and its added time.
    w = r["without_rerank"]
    assert set(w["recall_at"]) == set(r["recall_at"]) and w["rerank_ms_median"] > 0
    assert "without rerank: " in p.stdout and "rerank adds " in p.stdout
    # Verification only re-orders the first candidates: recall at 20 cannot change.
    assert w["recall_at"]["20"] == r["recall_at"]["20"]
    # The README's analysis of that record runs on it.
    analysis = subprocess.run(
        [sys.executable, "-m", "bench.verification", str(out)], capture_output=True, text=True, timeout=600
    )
    assert analysis.returncode == 0, analysis.stderr[-3000:]
    assert "AUC" in analysis.stdout


def test_check_backup_restore(ingested, fitted_models, tmp_path):
    models = ["--models-dir", str(fitted_models)]
    ok = geoloc("check", "--data-dir", str(ingested), *models)
    assert "ok: rows, images, codes and index agree" in ok.stdout and "30 indexed" in ok.stdout
    backup = tmp_path / "backup"
    out = geoloc("backup", str(backup), "--data-dir", str(ingested))
    assert "backed up 30 references (30 images" in out.stdout
    refused = geoloc("backup", str(backup), "--data-dir", str(ingested), check=False)
    assert refused.returncode == 2 and "not empty" in refused.stderr
    restored = tmp_path / "restored"
    geoloc("restore", str(backup), "--data-dir", str(restored))
    assert "ok:" in geoloc("check", "--data-dir", str(restored), *models).stdout
    photo = PENN / "photos" / "img_00000.jpg"
    res = json.loads(geoloc("locate", str(photo), "--top-k", "1", "--data-dir", str(restored), *models).stdout)
    assert res["candidates"][0]["label"] == "img_00000.jpg" and res["index"]["size"] == 30
    # Break the restored copy three ways: check names each.
    db = sqlite3.connect(restored / "references.sqlite")
    sha = db.execute("SELECT sha256, image_ext FROM refs WHERE id=2").fetchone()
    db.execute("UPDATE refs SET float_code=NULL WHERE id=3")
    db.commit()
    db.close()
    (restored / "images" / f"{sha[0]}.{sha[1]}").unlink()
    (restored / "images" / "stray.jpg").write_bytes(b"x")
    bad = geoloc("check", "--data-dir", str(restored), *models, check=False)
    assert bad.returncode == 1
    assert "image file is missing: 2" in bad.stderr and "stray.jpg" in bad.stderr and "without codes" in bad.stderr
    assert get_config(CONFIG).float_codes and np.isfinite(0)


def test_locate_command_with_rerank_and_regions(ingested, fitted_models):
    photo = PENN / "photos" / "img_00000.jpg"
    base = ["--data-dir", str(ingested), "--models-dir", str(fitted_models), "--top-k", "3"]
    res = json.loads(geoloc("locate", str(photo), "--rerank", "--lat", "39.9522", "--lon", "-75.1932",
                            "--radius-m", "300", *base).stdout)  # fmt: skip
    assert res["candidates"] and all("inliers" in c for c in res["candidates"]) and "rerank" in res["timings_ms"]
    assert res["candidates"][0]["label"] == "img_00000.jpg" and res["candidates"][0]["inliers"] > 0
    empty = json.loads(geoloc("locate", str(photo), "--bbox", "0,0,0.01,0.01", *base).stdout)
    assert empty["candidates"] == [] and empty["reason"] == "no references in the requested region"
    bad = geoloc("locate", str(photo), "--lat", "39.95", *base, check=False)
    assert bad.returncode == 2 and "lat, lon and radius_m together" in bad.stderr


def test_locate_compare_exif_says_how_far_the_answer_is(ingested, fitted_models):
    photo = PENN / "photos" / "img_00000.jpg"  # in the collection: its best candidate is itself
    p = geoloc("locate", str(photo), "--compare-exif", "--top-k", "3", "--data-dir", str(ingested),
               "--models-dir", str(fitted_models))  # fmt: skip
    check = json.loads(p.stdout)["exif_check"]
    assert check["best_candidate_m"] < 1 and "The best candidate is 0 m from there." in p.stderr


def test_a_verified_answer_is_judged_by_the_verified_rule(ingested, fitted_models):
    """/locate's core applies ``Calibration.for_answer``: two rules that disagree on purpose (every candidate
    at a 5 % chance unverified, 95 % verified) show which one judged each answer."""
    from dataclasses import asdict

    from app.engine.calibration import Calibration
    from app.engine.evidence import GLOBAL_NAMES, VERIFIED_NAMES

    def rule(names, intercept):
        n = len(names)
        return Calibration(
            names=tuple(names), mean=[0.0] * n, scale=[1.0] * n, coef=[0.0] * n, intercept=intercept,
            source="collection",
        )  # fmt: skip

    pipe = load_pipeline(fitted_models, CONFIG)
    pipe.calibration = rule(GLOBAL_NAMES, -3.0)
    pipe.calibration.verified = asdict(rule(GLOBAL_NAMES + VERIFIED_NAMES, 3.0))
    store = ReferenceStore(ingested)
    with store.code_stream() as stream:
        index = index_from_stream(pipe, stream.chunks)
    rgb = pipe.decode((PENN / "photos" / "img_00006.jpg").read_bytes()).rgb
    features = pipe.extract(rgb)
    refs = StoreReferences(store)
    plain = locate_features(pipe, index, refs, features, LocateOptions(top_k=10))
    verified = locate_features(pipe, index, refs, features, LocateOptions(top_k=10, rerank=True), rgb)
    assert {c.p_within_25m for c in plain.candidates} == {round(1 / (1 + np.exp(3.0)), 4)}
    assert {c.p_within_25m for c in verified.candidates} == {round(1 / (1 + np.exp(-3.0)), 4)}
    assert any(c.inliers is not None for c in verified.candidates)
