"""The served default filters a query's features through an SVM bank trained from the collection.

Own fixture, apart from the session's hybrid-bin models: the default ``hybrid`` configuration fitted on the
mini manifest with ``geoloc fit`` as a user runs it (no --svm-bank: the bank comes from the db rows), then a
real server, references added over HTTP, and a real photo located."""

import json
import shutil
import subprocess
import sys

import pytest

from app.engine.models.squeezenet import MODEL_FILENAME
from app.manifests import read_manifest
from tools.server_process import ServerProcess, wait_job

CONFIG = "hybrid"


@pytest.fixture(scope="module")
def bank_models(tmp_path_factory, models_dir, mini_manifest):
    """A models dir of its own: the built ONNX model and ``hybrid`` fitted with its collection bank."""
    d = tmp_path_factory.mktemp("svm-models")
    shutil.copy(models_dir / MODEL_FILENAME, d / MODEL_FILENAME)
    p = subprocess.run(
        [sys.executable, "-m", "app.cli", "fit", "--manifest", str(mini_manifest), "--config", CONFIG]
        + ["--models-dir", str(d)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert p.returncode == 0, p.stderr
    assert "SVM bank (contrastive, from collection)" in p.stdout
    return d


def test_locate_keeps_fewer_features_than_it_extracts(tmp_path, bank_models, mini_manifest):
    bank = json.loads((bank_models / "pipelines" / CONFIG / "svm_bank.json").read_text())
    assert bank["fit"]["source"]["kind"] == "collection" and bank["fit"]["source"]["sampled_references"] > 0
    assert bank["fit"]["chosen_keep_fraction"] < 1.0  # the default rule filters; it never switches itself off

    rows = read_manifest(mini_manifest)
    db = [r for r in rows if r.split == "db" and "/photos/" in str(r.image)]  # one photo per capture
    query = next(r for r in rows if r.split == "query" and "/photos/" in str(r.image))
    extra = {"GEOLOC_ORT_THREADS": "1"}
    with ServerProcess(tmp_path / "data", bank_models, CONFIG, extra_env=extra) as server:
        c = server.client
        files = [("image", (r.image.name, r.image.read_bytes(), "image/jpeg")) for r in db]
        meta = [{"lat": r.lat, "lon": r.lon, "label": r.image.name} for r in db]
        added = c.post("/references", files=files, data={"metadata": json.dumps(meta)})
        assert added.status_code == 202, added.text
        assert wait_job(c, added.json()["job_id"])["status"] == "done"

        loc = c.post("/locate", files=[("image", ("q.jpg", query.image.read_bytes(), "image/jpeg"))])
        assert loc.status_code == 200, loc.text
        res = loc.json()
    features = res["features"]
    assert features["extracted"] > 100
    assert bank["params"]["min_keep"] <= features["kept"] < features["extracted"]
    assert "svm" in res["timings_ms"] and res["candidates"] and res["index"]["size"] == len(db)
