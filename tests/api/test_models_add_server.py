"""A model added with `geoloc models add` (another input size, rule, colour order and normalisation than any
built-in, and a global vector for output) fits, ingests and locates through a real uvicorn server; a running
collection moves to it with `geoloc refit` (the atomic switch, no restart); its backup restores and
`geoloc check` verifies its files by their sha256."""

from __future__ import annotations

import os
import shutil
import time

import pytest

from app.engine.pipeline import PipelineSource
from app.ingestion.encoding.ray import model_files
from app.manifests import read_manifest
from tests.api.conftest import CONFIG, ServerProcess
from tests.engine.test_models_add import export_squeezenet_vector, geoloc, squeezenet_spec

NAME = "sqv"


@pytest.fixture(scope="module")
def added_models(tmp_path_factory, fitted_models, models_dir):
    """A models dir of this module's: the session's SqueezeNet and fitted hybrid-bin (linked), and the
    SqueezeNet vector export added under ``sqv`` through the command."""
    from app.engine.models.squeezenet import MODEL_FILENAME

    d = tmp_path_factory.mktemp("models_add_server")
    onnx_path, mean_bgr = export_squeezenet_vector(models_dir, d / "sqv.onnx")
    (d / "sqv.json").write_text(squeezenet_spec(mean_bgr))
    models = d / "models"
    (models / "pipelines").mkdir(parents=True)
    os.symlink(fitted_models / MODEL_FILENAME, models / MODEL_FILENAME)
    os.symlink(fitted_models / "pipelines" / CONFIG, models / "pipelines" / CONFIG)
    out = geoloc(
        "models", "add", NAME, "--onnx", str(onnx_path), "--spec", str(d / "sqv.json"), "--models-dir", str(models)
    )
    assert f"configurations: {NAME}, {NAME}-hybrid" in out.stdout
    return models


def _server(data, models, config):
    return ServerProcess(data, models, config, extra_env={"GEOLOC_ORT_THREADS": "1"})


def _locate(client, path):
    r = client.post("/locate", files=[("image", ("q.jpg", path.read_bytes(), "image/jpeg"))], data={"top_k": 3})
    assert r.status_code == 200, r.text
    return r.json()


def test_models_add_hybrid_fits_ingests_and_locates_through_a_server(added_models, mini_manifest, tmp_path):
    config = f"{NAME}-hybrid"
    m, models = str(mini_manifest), str(added_models)
    fit = geoloc(
        "fit",
        "--manifest",
        m,
        "--config",
        config,
        "--models-dir",
        models,
        "--svm-bank",
        "none",
        "--calibration-sample",
        "20",
    )
    assert f"saved {added_models / 'pipelines' / config}" in fit.stdout, fit.stdout
    # What Ray ships to its actors (`geoloc ingest --ray`): the added model's files, as a built-in's.
    shipped = model_files(PipelineSource.default(added_models, config))
    assert {f"added/{NAME}/model.onnx", f"added/{NAME}/spec.json", f"added/{NAME}/SHA256SUMS"} <= set(shipped)
    data = tmp_path / "data"
    out = geoloc(
        "ingest", "--manifest", m, "--split", "db", "--config", config, "--data-dir", str(data), "--models-dir", models
    )
    assert "ingested 30 new references" in out.stdout and f"config {config}" in out.stdout, out.stdout
    rows = read_manifest(mini_manifest)
    db = [r for r in rows if r.split == "db"]
    with _server(data, added_models, config) as s:
        assert s.client.get("/ready").json()["config"] == config
        for row in db[:3]:  # a reference's own photo finds itself first, at its position
            answer = _locate(s.client, row.image)
            top = answer["candidates"][0]
            assert top["score"] > 0.99 and abs(top["lat"] - row.lat) < 1e-6 and abs(top["lon"] - row.lon) < 1e-6
        query = next(r for r in rows if r.split == "query")
        assert len(_locate(s.client, query.image)["candidates"]) == 3
    assert (
        "ok: rows, images, codes and index agree"
        in geoloc("check", "--data-dir", str(data), "--models-dir", models).stdout
    )


def test_models_add_refit_moves_a_running_collection_to_the_added_model(
    added_models, mini_collection, mini_manifest, tmp_path
):
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)  # hybrid-bin, generation 0
    photo = next(r for r in read_manifest(mini_manifest) if r.split == "db").image
    with _server(data, added_models, CONFIG) as s:
        own_id = _locate(s.client, photo)["candidates"][0]["reference_id"]
        out = geoloc(
            "refit",
            "--config",
            NAME,
            "--data-dir",
            str(data),
            "--models-dir",
            str(added_models),
            "--sample",
            "12",
            "--svm-bank",
            "none",
            "--seed",
            "7",
        )
        assert f"generation 1 ({NAME}," in out.stdout and "30 references re-encoded" in out.stdout, out.stdout
        deadline = time.time() + 120
        while s.client.get("/ready").json().get("generation") != 1 and time.time() < deadline:
            time.sleep(0.5)
        after = _locate(s.client, photo)  # the same server, no restart, now on the added model
    assert after["index"]["generation"] == 1 and after["candidates"][0]["reference_id"] == own_id
    assert after["candidates"][0]["score"] > 0.99
    # A backup restores onto the same models dir; `geoloc check` verifies the added model's files.
    geoloc("backup", str(tmp_path / "backup"), "--data-dir", str(data))
    restored = tmp_path / "restored"
    geoloc("restore", str(tmp_path / "backup"), "--data-dir", str(restored))
    ok = geoloc("check", "--data-dir", str(restored), "--models-dir", str(added_models))
    assert f"pipeline: pipelines/{NAME}-g1, generation 1" in ok.stdout, ok.stdout
    # The same check on a models dir whose copy of the model was changed names it (exit 1).
    changed = tmp_path / "changed-models"
    shutil.copytree(added_models, changed, symlinks=True)
    with open(changed / "added" / NAME / "model.onnx", "ab") as f:
        f.write(b"\0")
    bad = geoloc("check", "--data-dir", str(restored), "--models-dir", str(changed), check=False)
    assert bad.returncode == 1 and "model.onnx is not the file that was added" in bad.stderr, bad.stderr
