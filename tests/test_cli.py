"""The geoloc command end to end, as a user runs it (real subprocesses, real files)."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import PENN, SQUEEZENET_IR


def geoloc(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    p = subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, env=env, timeout=600)
    if check and p.returncode != 0:
        raise AssertionError(f"geoloc {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("cli")
    geoloc("models", "build", "--from", str(SQUEEZENET_IR), "--models-dir", str(d / "models"))
    return d


def test_build_fit_ingest_locate(workdir, mini_manifest):
    m, data, models = str(mini_manifest), str(workdir / "index"), str(workdir / "models")
    assert (workdir / "models" / "squeezenet1_1.onnx").exists()
    # No bank here: this test checks exact self-retrieval (a db photo's own code, all its features).
    out = geoloc(
        "fit", "--manifest", m, "--config", "hybrid-bin", "--models-dir", models, "--svm-bank", "none",
        "--calibration-sample", "20", "--calibrate-rerank",
    )  # fmt: skip
    assert "saved" in out.stdout and "no SVM bank" in out.stdout
    # --calibrate-rerank: the 20 are located again with verification, for the rule of verified answers.
    assert "verified_sampled 20" in out.stdout, out.stdout
    # The 10 db captures of the mini manifest (20 sampled of their 30 images): calibrated or, too few right
    # answers, the conservative rule; either way it says which, and how many references it sampled.
    assert re.search(r"calibration \((collection|conservative)\): .*sampled 20", out.stdout), out.stdout
    assert (workdir / "models" / "pipelines" / "hybrid-bin" / "calibration.json").exists()
    manifest = json.loads((workdir / "models" / "pipelines" / "hybrid-bin" / "pipeline.json").read_text())
    assert manifest["config"]["name"] == "hybrid-bin" and manifest["bits"] > 0

    out = geoloc(
        "ingest", "--manifest", m, "--split", "db", "--config", "hybrid-bin", "--data-dir", data, "--models-dir", models
    )
    assert "ingested 30 new references" in out.stdout
    again = geoloc(
        "ingest", "--manifest", m, "--split", "db", "--config", "hybrid-bin", "--data-dir", data, "--models-dir", models
    )
    assert "ingested 0 new references (30 already present)" in again.stdout

    photo = PENN / "photos" / "img_00000.jpg"  # a db photo: must come back first
    res = json.loads(geoloc("locate", str(photo), "--top-k", "3", "--data-dir", data, "--models-dir", models).stdout)
    assert res["config"] == "hybrid-bin" and res["mode"] == "two-stage"
    assert res["candidates"][0]["label"] == "img_00000.jpg" and res["candidates"][0]["score"] > 0.95
    assert res["index"]["size"] == 30 and res["features"]["extracted"] > 100

    res = json.loads(
        geoloc("locate", str(photo), "--mode", "binary", "--data-dir", data, "--models-dir", models).stdout
    )
    assert res["mode"] == "binary"
    # The calibration located its sample in two-stage search: binary mode's Hamming similarities are on
    # another scale, so they are not read through it (no probabilities, the conservative rule, and why).
    calibration = json.loads((workdir / "models" / "pipelines" / "hybrid-bin" / "calibration.json").read_text())
    assert all(c["p_within_25m"] is None for c in res["candidates"])
    assert (
        calibration["source"] == "conservative"
        or res["estimate"] is not None
        or ("calibrated for two-stage search" in res["reason"])
    ), res["reason"]
    bad = geoloc("locate", str(photo), "--mode", "float-ish", "--data-dir", data, "--models-dir", models, check=False)
    assert bad.returncode == 2 and "serves two-stage" in bad.stderr
    bad = geoloc(
        "locate", str(SQUEEZENET_IR / "squeezenet1.1.labels"), "--data-dir", data, "--models-dir", models, check=False
    )
    assert bad.returncode == 2 and "not a JPEG" in bad.stderr
    # --brief: the answer in words (a db photo: its own reference and crops agree on the spot).
    brief = geoloc("locate", str(photo), "--brief", "--compare-exif", "--data-dir", data, "--models-dir", models)
    # Calibrated on 20 of these 30 references (a tiny sample, no threshold reaches 90 %), the rule gives no
    # confident answer, but a reference's own photo scores above anything its calibration saw: never
    # "not in this collection", and the reference itself comes first.
    assert brief.stdout.startswith(("Taken within ", "Possible only")), brief.stdout
    assert "img_00000.jpg" in brief.stdout and "not in this collection" not in brief.stdout, brief.stdout
    assert "EXIF GPS" in brief.stdout and not brief.stdout.lstrip().startswith("{")


def test_the_fast_configurations_fit_ingest_and_locate_at_their_sizes(workdir, mini_manifest):
    """hybrid-fast and hybrid-faster are the default on fewer pixels and nothing else: the same
    stages end to end, with a db photo found first by its own code."""
    from app.engine.configs import get_config
    from app.engine.pipeline import Pipeline

    base = get_config("hybrid").model_dump()
    for name, sizes in (("hybrid-fast", (512, 448)), ("hybrid-faster", (512, 336))):
        c = get_config(name)
        assert {k for k, v in c.model_dump().items() if base[k] != v} <= {
            "name", "description", "local_long_side", "cnn_short_side",
        }  # fmt: skip
        assert Pipeline(c, models_dir=workdir / "models").decode_sides == sizes
    m, data, models = str(mini_manifest), str(workdir / "index-faster"), str(workdir / "models")
    geoloc(
        "fit", "--manifest", m, "--config", "hybrid-faster", "--models-dir", models, "--svm-bank", "none",
        "--calibration-sample", "20",
    )  # fmt: skip
    geoloc(
        "ingest", "--manifest", m, "--split", "db", "--config", "hybrid-faster", "--data-dir", data,
        "--models-dir", models,
    )  # fmt: skip
    photo = PENN / "photos" / "img_00000.jpg"  # a db photo
    res = json.loads(geoloc("locate", str(photo), "--top-k", "3", "--data-dir", data, "--models-dir", models).stdout)
    assert res["config"] == "hybrid-faster" and res["index"]["size"] == 30
    assert res["candidates"][0]["label"] == "img_00000.jpg" and res["candidates"][0]["score"] > 0.95


def test_eval_writes_the_report(workdir, mini_manifest):
    out_json = workdir / "eval" / "hybrid.json"
    p = geoloc(
        "eval",
        "--manifest",
        str(mini_manifest),
        "--config",
        "hybrid",
        "--models-dir",
        str(workdir / "models"),
        "--json",
        str(out_json),
        "--folds",
        "2",
        "--absent-radius",
        "100",
        "--cache",
        str(workdir / "eval-cache"),  # test_eval_runs_one_fold reads the features from it
    )
    assert "Recall@1/5/10/20" in p.stdout and "absent places" in p.stdout and "  fold 2:" in p.stdout
    r = json.loads(out_json.read_text())
    assert r["config"] == "hybrid" and r["folds"] == 2 and r["radius_m"] == 25
    assert set(r["recall_at"]) == {"1", "5", "10", "20"} and all(0 <= v <= 1 for v in r["recall_at"].values())
    assert r["n_query"] == 39 and r["n_db"] > 0  # 13 non-train captures x 3 images, each a query once
    assert {"total", "decode", "local_features", "cnn", "aggregate", "search"} <= set(r["ms_per_query"])
    assert r["bytes_per_reference"] == 4 * 256 or r["bytes_per_reference"] < 4 * 256
    assert {"median", "p90", "confident_within_radius"} <= set(r["estimate_error_m"])
    assert out_json.with_suffix(".png").stat().st_size > 1000
    a = r["answers"]  # answer quality: pooled, per fold, and on the simulated absent places
    assert len(r["answers_per_fold"]) == 2 and len(r["calibration_per_fold"]) == 2
    assert 0 <= a["coverage"] <= 1 and a["absent_radius_m"] == 100 and 0 <= a["absent_confident"] <= 1
    assert "precision_at_2x_radius" in a and "within twice the radius" in p.stdout
    assert sum(a["reason_codes"].values()) == 39 == sum(a["absent_reason_codes"].values())
    # The disc's figures: the estimate share, the truth within the stated radius (overall, weakest quartile),
    # the median and 90th-percentile radius (None without an estimate), and no_match's absent share.
    assert a["estimate_share"] == a["coverage"] and r["fold"] is None
    assert {"radius_coverage", "radius_coverage_weakest_quartile", "median_radius_m", "p90_radius_m"} <= set(a)
    if a["median_radius_m"] is not None:
        assert a["median_radius_m"] <= a["p90_radius_m"] and 0 <= a["radius_coverage"] <= 1
    no_match = a["reason_codes"].get("no_match", 0) + a["absent_reason_codes"].get("no_match", 0)
    assert a["no_match_answers"] == no_match and a["no_match_absent_at_m"] == 100
    assert (a["no_match_absent_share"] is None) == (no_match == 0)
    if no_match:
        assert 0 <= a["no_match_absent_share"] <= 1 and "of which the place was absent" in p.stdout


def test_eval_runs_one_fold(workdir, mini_manifest):
    """`geoloc eval --folds 2 --fold 1`: the second fold alone (its queries, its fit), said so."""
    out_json = workdir / "eval" / "fold1.json"
    args = ["eval", "--manifest", str(mini_manifest), "--config", "hybrid", "--models-dir", str(workdir / "models")]
    cache = ["--cache", str(workdir / "eval-cache")]  # the features test_eval_writes_the_report extracted, if it ran
    p = geoloc(*args, *cache, "--folds", "2", "--fold", "1", "--json", str(out_json))
    assert "folds 2 (fold 1 only)" in p.stdout and "  fold 2:" not in p.stdout
    r = json.loads(out_json.read_text())
    assert r["folds"] == 2 and r["fold"] == 1 and len(r["answers_per_fold"]) == 1
    assert 0 < r["n_query"] < 39 and {q["fold"] for q in r["queries"]} == {1}
    assert r["answers"]["no_match_absent_at_m"] == 25  # no --absent-radius: --radius-m
    bad = geoloc(*args, "--folds", "2", "--fold", "2", check=False)
    assert bad.returncode == 2 and "--fold must be from 0 to 1" in bad.stderr


def test_unknown_config_is_a_clear_error(workdir, mini_manifest):
    p = geoloc("eval", "--manifest", str(mini_manifest), "--config", "nope", check=False)
    assert p.returncode == 2 and "unknown configuration 'nope'" in p.stderr


def test_fit_with_svm_bank_and_the_ablation(workdir, mini_manifest):
    models = str(workdir / "models")
    out = geoloc(
        "fit",
        "--manifest",
        str(mini_manifest),
        "--config",
        "hybrid",
        "--models-dir",
        models,
        "--svm-bank",
        "train",
        "--svm-bank-kind",
        "confusers",
    )
    assert "SVM bank (confusers, from train)" in out.stdout
    bank_dir = workdir / "models" / "pipelines" / "hybrid"
    manifest = json.loads((bank_dir / "svm_bank.json").read_text())
    assert manifest["params"]["kind"] == "confusers" and manifest["fit"]["clusters"]
    assert {"numpy", "scikit-learn"} <= set(manifest["libraries"]) and manifest["fit"]["data_hash"]

    out_json = workdir / "eval" / "neg.json"
    geoloc(
        "eval",
        "--manifest",
        str(mini_manifest),
        "--config",
        "hybrid",
        "--models-dir",
        models,
        "--svm-bank",
        "negative",
        "--json",
        str(out_json),
    )
    r = json.loads(out_json.read_text())
    assert r["svm_bank"]["selection"] == "negative" and r["svm_bank"]["kind"] == "contrastive"
    assert 0 < r["svm_bank"]["kept_fraction_median"] <= 1 and "svm" in r["ms_per_query"]
    assert r["svm_bank"]["folds"][0]["training"]["negative_radius_m"] >= 75


def test_fit_trains_the_bank_from_the_collection_unless_the_configuration_says_none(workdir, mini_manifest):
    models = workdir / "models"
    out = geoloc("fit", "--manifest", str(mini_manifest), "--config", "hybrid", "--models-dir", str(models))
    assert "SVM bank (contrastive, from collection)" in out.stdout
    bank = json.loads((models / "pipelines" / "hybrid" / "svm_bank.json").read_text())["fit"]
    # 30 db images (10 captures) sampled as training photos, plus the 9 train images.
    assert bank["source"] == {
        "kind": "collection",
        "references": 30,
        "sampled_references": 30,
        "train_photos": 9,
        "max_photos": bank["source"]["max_photos"],
    }
    assert bank["training"]["labelled_positive"] > 0 and bank["training"]["labelled_negative"] > 0

    out = geoloc("fit", "--manifest", str(mini_manifest), "--config", "hybrid-nobank", "--models-dir", str(models))
    assert "no SVM bank" in out.stdout
    assert not (models / "pipelines" / "hybrid-nobank" / "svm_bank.json").exists()
    bad = geoloc("fit", "--manifest", str(mini_manifest), "--svm-bank", "everything", check=False)
    assert bad.returncode == 2 and "--svm-bank must be one of collection, train, none" in bad.stderr


def _write_manifest(path: Path, rows: list[tuple[str, str, str]], penn_index) -> Path:
    """rows: (image path relative to PENN, split, group); positions from the penn index by photo id."""
    pos = {r["photo_id"]: (r["lat"], r["lon"]) for r in penn_index}
    lines = ["image,lat,lon,split,group"]
    for image, split, group in rows:
        lat, lon = pos[Path(image).stem[:9]]
        lines.append(f"{PENN / image},{lat},{lon},{split},{group}")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_eval_names_a_manifest_that_leaves_nothing_to_fit_on(workdir, penn_index, tmp_path):
    # Every db row is a crop of a query photo, in the query's group: once the queries' groups are set
    # aside, no reference is left to fit the pipeline on or to search.
    m = _write_manifest(
        tmp_path / "shared-groups.csv",
        [
            ("photos/img_00000.jpg", "query", "a"),
            ("crops/img_00000_0.jpg", "db", "a"),
            ("photos/img_00001.jpg", "query", "b"),
            ("crops/img_00001_0.jpg", "db", "b"),
        ],
        penn_index,
    )
    p = geoloc("eval", "--manifest", str(m), "--config", "hybrid", "--models-dir", str(workdir / "models"), check=False)
    assert p.returncode == 2, p.stderr
    assert "leaves no db row to fit on" in p.stderr and "every db row shares a group with a query" in p.stderr
    assert "groups a, b" in p.stderr and "Traceback" not in p.stderr

    # Two groups rotated over three folds: one fold has no query at all.
    p = geoloc(
        "eval",
        "--manifest",
        str(m),
        "--folds",
        "3",
        "--config",
        "hybrid",
        "--models-dir",
        str(workdir / "models"),
        check=False,
    )
    assert p.returncode == 2 and "has no query" in p.stderr and "Traceback" not in p.stderr


def test_every_failure_is_one_line_and_a_documented_exit_code(tmp_path):
    """`geoloc locate missing.jpg` once printed a long traceback. Every failure: one line on stderr,
    an exit code of docs/guide.md's table (app.cli.EXIT_CODES); --debug adds the traceback."""
    from app.cli import EXIT_CODES

    guide = (Path(__file__).resolve().parents[1] / "docs" / "guide.md").read_text()
    for code, meaning in EXIT_CODES.items():
        assert f"| {code} | {meaning} |" in guide, code
    photo = str(PENN / "photos" / "img_00000.jpg")
    empty = ("--data-dir", str(tmp_path / "data"), "--models-dir", str(tmp_path / "models"))
    cases = [
        (("locate", str(tmp_path / "missing.jpg"), *empty), 2, "missing.jpg: No such file or directory"),
        (("locate", photo, "--bogus"), 2, "No such option: --bogus"),
        (("locate",), 2, "give one photo (several, or a folder, with --sequence)"),
        (("frobnicate",), 2, "No such command"),
        (("locate", photo, *empty), 3, "no fitted pipeline"),
        (("eval", "--manifest", str(tmp_path / "none.csv"), "--models-dir", str(tmp_path)), 2, "none.csv"),
    ]
    for args, code, words in cases:
        p = geoloc(*args, check=False)
        lines = p.stderr.strip().splitlines()
        assert p.returncode == code and len(lines) == 1 and words in lines[0], (args, p.returncode, p.stderr)
        assert lines[0].startswith("error: ") and "Traceback" not in p.stderr + p.stdout
    debug = geoloc("locate", str(tmp_path / "missing.jpg"), "--debug", *empty, check=False)
    assert debug.returncode == 2 and "Traceback" in debug.stderr and "FileNotFoundError" in debug.stderr
    assert debug.stderr.strip().splitlines()[-1].startswith("error: ")


def test_brief_says_what_no_match_measures_and_an_estimate_its_disc():
    """`geoloc locate --brief` words a no_match answer as the page does (the JSON shape of /locate): no
    reference looks like the photo, never that the place is absent; an estimate states its disc and rate."""
    from app.cli import _in_words

    cand = {"reference_id": 3, "label": "a.jpg", "lat": 39.95, "lon": -75.19, "score": 0.58, "p_within_25m": 0.03}
    out = {
        "candidates": [cand, {**cand, "reference_id": 4, "lat": 39.951}],
        "estimate": None,
        "reason": "no reference looks like this photo: no candidate has a 10% chance of lying within 25 m of where "
        "it was taken (best 3%)",
        "reason_code": "no_match",
    }
    words = _in_words(out)
    assert words.startswith("No reference looks like this photo (no candidate has a") and "reference 3 (a.jpg)" in words
    assert "not in this collection" not in words and "absent" not in words
    assert _in_words({**out, "reason_code": "ambiguous"}).startswith("Possible only")
    estimate = {"lat": 39.95, "lon": -75.19, "radius_m": 60.0, "radius_rate": 0.9, "confidence": 0.8}
    cands = [{**c, "distance_m": 0.0} for c in out["candidates"]]
    words = _in_words({**out, "candidates": cands, "estimate": estimate, "reason": None, "reason_code": None})
    assert words.startswith("Taken within 60 m of 39.95000,-75.19000: 9 in 10 such answers are (confidence 0.80"), words
