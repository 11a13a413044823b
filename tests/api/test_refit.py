"""Re-fit and re-index (`geoloc refit`): a new generation of pipeline and codes, switched atomically while a
real server keeps answering; uploads and deletions made during the re-index reach the new generation; a
worker's codes from the old pipeline are never recorded after the switch; an interrupted re-index leaves
the old generation serving and a re-run continues it."""

import json
import shutil
import threading
import time

import numpy as np
import pytest

from app.engine.imageio import ImageLimits
from app.ingestion.completion import complete, encode_batch
from app.ingestion.encoding.items import EncodeItem
from app.ingestion.encoding.local import LocalEngine
from app.jobs.refit import RefitOptions, fit_generation, reindex, switch
from app.manifests import read_manifest
from app.storage.store import NewReference, ReferenceStore
from app.usecases.service import GeolocService
from tests.api.conftest import CONFIG, Server, wait_job
from tests.test_cli import geoloc


@pytest.fixture
def template(mini_collection):
    """The session's data dir of the mini manifest's 30 db images, generation 0 (copied by each test)."""
    return mini_collection


@pytest.fixture(scope="module")
def rows(mini_manifest):
    return read_manifest(mini_manifest)


def _copy(template, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(template, data)
    return data


def _locate(client, path, top_k=3):
    r = client.post("/locate", files=[("image", ("q.jpg", path.read_bytes(), "image/jpeg"))], data={"top_k": top_k})
    return r


def _wait_generation(client, generation, timeout=120.0):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if client.get("/ready").json().get("generation") == generation:
            return
        time.sleep(0.2)
    raise TimeoutError(f"the server never switched to generation {generation}")


def _meta(data) -> dict:
    store = ReferenceStore(data)
    try:
        return dict(store.db.execute("SELECT key, value FROM meta").fetchall())
    finally:
        store.close()


def test_refit_switches_generation_while_the_server_keeps_answering(template, fitted_models, tmp_path, rows):
    data = _copy(template, tmp_path)
    before = ReferenceStore(data).all_codes()
    photo = next(r for r in rows if r.split == "db").image
    answers, failures = [], []
    stop = threading.Event()
    with Server(data, fitted_models) as s:
        own_id = _locate(s.client, photo).json()["candidates"][0]["reference_id"]

        def hammer():
            while not stop.is_set():
                r = _locate(s.client, photo)
                (answers if r.status_code == 200 else failures).append(r.json() if r.status_code == 200 else r.text)

        t = threading.Thread(target=hammer)
        t.start()
        try:
            out = geoloc(
                "refit", "--data-dir", str(data), "--models-dir", str(fitted_models),
                "--sample", "12", "--svm-bank", "none", "--seed", "7",
            )  # fmt: skip
            _wait_generation(s.client, 1)  # no restart: the running server swaps pipeline and index itself
            after = _locate(s.client, photo).json()
        finally:
            stop.set()
            t.join()
    assert "switched" in out.stdout and "generation 1" in out.stdout and "30 references re-encoded" in out.stdout
    assert not failures, failures[:3]
    generations = [a["index"]["generation"] for a in answers]
    assert generations[0] == 0 and set(generations) <= {0, 1}  # the old generation answered until the switch
    assert {k: v for k, v in after["index"].items() if k != "extent"} == {
        "size": 30,
        "version": after["index"]["version"],
        "generation": 1,
    }
    assert after["index"]["extent"] == answers[0]["index"]["extent"]  # the same references, the same extent
    assert after["candidates"][0]["reference_id"] == own_id and after["candidates"][0]["score"] > 0.99
    meta = _meta(data)
    assert meta["generation"] == "1" and meta["pipeline"] == f"pipelines/{CONFIG}-g1" and meta["config"] == CONFIG
    assert (data / meta["pipeline"] / "pipeline.json").exists()
    assert "reindex_target" not in meta
    now = ReferenceStore(data).all_codes()
    assert list(now[1]) == list(before[1])  # the same references ...
    changed = int((now[3] != before[3]).any(axis=1).sum())
    assert changed > 20  # ... with new codes
    # A second process opening the data dir uses the new generation.
    cli = json.loads(geoloc("locate", str(photo), "--data-dir", str(data), "--models-dir", str(fitted_models)).stdout)
    assert cli["index"]["generation"] == 1 and cli["candidates"][0]["reference_id"] == own_id
    snapshot = json.loads((data / "index.json").read_text())  # the server's last one is of the new generation
    assert snapshot["generation"] == 1 and snapshot["fingerprint"] == meta["fingerprint"]


def test_uploads_and_deletions_during_the_reindex_reach_the_new_generation(template, fitted_models, tmp_path, rows):
    data = _copy(template, tmp_path)
    store = ReferenceStore(data)
    target, _ = fit_generation(store, fitted_models, RefitOptions(sample=12, svm_bank="none", seed=5))
    store.start_reindex(target)
    engine = LocalEngine(target.source(data, fitted_models).load(), ImageLimits())
    first, _ = reindex(store, target, engine, batch=4, limit=8)  # the re-index is half-way ...
    assert first == 8 and switch(store, target) is None  # ... and cannot switch yet
    ids = [int(i) for i in store.indexed_ids()]
    gone = [ids[0], ids[-1]]  # one already re-encoded, one not yet
    new_photo = next(r for r in rows if r.split == "query")
    with Server(data, fitted_models) as s:
        acc = s.client.post(
            "/references",
            files=[("image", ("new.jpg", new_photo.image.read_bytes(), "image/jpeg"))],
            data={"metadata": json.dumps([{"lat": new_photo.lat, "lon": new_photo.lon}])},
        ).json()
        assert wait_job(s.client, acc["job_id"])["status"] == "done"  # indexed by the old generation
        new_id = acc["reference_ids"][0]
        for i in gone:
            assert s.client.delete(f"/references/{i}").status_code == 200
        rest, failed = reindex(store, target, engine, batch=4)
        assert rest == 30 - 8 - 1 + 1 and failed == 0  # the rest, minus the deleted one, plus the upload
        assert switch(store, target) == 1
        _wait_generation(s.client, 1)
        found = _locate(s.client, new_photo.image, top_k=40).json()
        assert found["index"]["generation"] == 1 and found["index"]["size"] == 29
        assert found["candidates"][0]["reference_id"] == new_id
        assert not set(gone) & {c["reference_id"] for c in found["candidates"]}


def test_a_stale_worker_never_records_old_codes(template, fitted_models, tmp_path, rows):
    data = _copy(template, tmp_path)
    store = ReferenceStore(data)
    old = GeolocService.open(data, fitted_models, CONFIG)
    old_fp = old.pipeline.fingerprint
    target, _ = fit_generation(store, fitted_models, RefitOptions(sample=12, svm_bank="none", seed=3))
    store.start_reindex(target)
    engine = LocalEngine(target.source(data, fitted_models).load(), ImageLimits())
    reindex(store, target, engine, batch=8)
    assert switch(store, target) == 1
    # An upload accepted now, encoded by a worker that still holds generation 0.
    photo = next(r for r in rows if r.split == "query")
    (((ref_id, _),), _) = old.store.add_many([NewReference(photo.image.read_bytes(), "jpeg", 1.0, 2.0)])
    stale = encode_batch(old, old.store.pending(10))
    assert stale[0].fingerprint == old_fp
    assert complete(old, stale) == []  # not recorded: the data dir uses generation 1 now
    assert old.store.get(ref_id).status == "pending"
    # ... and the service loaded generation 1 before returning, so its next batch is encoded by it.
    assert old.collection.generation == 1 and old.pipeline.fingerprint == target.fingerprint
    assert complete(old, encode_batch(old, old.store.pending(10))) == [ref_id]
    row = old.store.db.execute("SELECT binary_code FROM refs WHERE id=?", (ref_id,)).fetchone()
    fresh = next(engine.run([EncodeItem(ref_id, old.store.image_path(ref_id))]))
    assert np.array_equal(np.frombuffer(row[0], np.uint8), fresh.binary_code)


def test_an_interrupted_reindex_leaves_the_old_generation_and_a_rerun_continues(template, fitted_models, tmp_path):
    data = _copy(template, tmp_path)
    store = ReferenceStore(data)
    target, _ = fit_generation(store, fitted_models, RefitOptions(sample=12, svm_bank="none", seed=9))
    store.start_reindex(target)
    engine = LocalEngine(target.source(data, fitted_models).load(), ImageLimits())
    assert reindex(store, target, engine, batch=3, limit=6) == (6, 0)  # then the process dies
    store.close()
    meta = _meta(data)
    assert meta.get("generation", "0") == "0" and json.loads(meta["reindex_target"])["generation"] == 1
    photo = next(iter((data / "images").iterdir()))
    cli = json.loads(geoloc("locate", str(photo), "--data-dir", str(data), "--models-dir", str(fitted_models)).stdout)
    assert cli["index"]["generation"] == 0 and cli["candidates"][0]["score"] > 0.99  # the old one still serves
    out = geoloc("refit", "--data-dir", str(data), "--models-dir", str(fitted_models)).stdout
    assert "continued an interrupted re-index" in out and "24 references re-encoded" in out
    meta = _meta(data)
    assert meta["generation"] == "1" and meta["fingerprint"] == target.fingerprint
    cli = json.loads(geoloc("locate", str(photo), "--data-dir", str(data), "--models-dir", str(fitted_models)).stdout)
    assert cli["index"]["generation"] == 1 and cli["candidates"][0]["score"] > 0.99
    # A backup carries the re-fitted pipeline: the restored copy checks clean on generation 1.
    geoloc("backup", str(tmp_path / "backup"), "--data-dir", str(data))
    geoloc("restore", str(tmp_path / "backup"), "--data-dir", str(tmp_path / "restored"))
    check = geoloc("check", "--data-dir", str(tmp_path / "restored"), "--models-dir", str(fitted_models)).stdout
    assert f"pipelines/{CONFIG}-g1, generation 1" in check and "ok:" in check


@pytest.mark.ray
def test_refit_on_ray_gives_the_codes_of_the_local_path(template, fitted_models, tmp_path):
    """`geoloc refit --ray local`: the re-fitted pipeline travels to the actors (it lives in the data dir,
    not the models dir) and the new generation's codes equal those of a local re-index."""
    codes = {}
    for engine, extra in (("local", ()), ("ray", ("--ray", "local", "--workers", "2"))):
        data = _copy(template, tmp_path / engine)
        out = geoloc(
            "refit", "--data-dir", str(data), "--models-dir", str(fitted_models),
            "--sample", "12", "--svm-bank", "none", "--seed", "3", *extra,
        ).stdout  # fmt: skip
        assert "30 references re-encoded" in out, out
        meta = _meta(data)
        assert meta["generation"] == "1"
        store = ReferenceStore(data)
        try:
            _, ids, fcodes, bcodes = store.all_codes()
        finally:
            store.close()
        codes[engine] = (meta["fingerprint"], dict(zip(ids.tolist(), zip(fcodes, bcodes, strict=True), strict=True)))
    (fp_local, local), (fp_ray, ray) = codes["local"], codes["ray"]
    assert fp_local == fp_ray  # the same seeded fit
    assert local.keys() == ray.keys() and len(local) == 30
    for i, (f, b) in local.items():
        assert np.allclose(f, ray[i][0], atol=1e-5)
        assert np.unpackbits(b ^ ray[i][1]).sum() <= 2


def test_refit_trains_the_bank_on_the_references_or_a_train_manifest(template, fitted_models, tmp_path, mini_manifest):
    """The SVM bank of a re-fit: from the stored references themselves, then (a second generation) from the
    train manifest's photos; each generation's folder holds its bank and says where it learnt."""
    data = _copy(template, tmp_path)
    base = ["refit", "--data-dir", str(data), "--models-dir", str(fitted_models), "--sample", "20", "--seed", "1"]
    for generation, extra, source in (
        (1, ["--svm-bank", "collection"], "collection"),
        (2, ["--train-manifest", str(mini_manifest)], "train"),  # train is the default with a manifest
    ):
        out = geoloc(*base, *extra).stdout
        assert "30 references re-encoded" in out, out
        meta = _meta(data)
        assert meta["generation"] == str(generation)
        folder = data / meta["pipeline"]
        assert folder.name == f"{CONFIG}-g{generation}"
        assert json.loads((folder / "pipeline.json").read_text())["svm_bank_source"] == source
        bank = json.loads((folder / "svm_bank.json").read_text())
        assert bank["fit"]["n_features"] > 0 and len(bank["fit"]["clusters"]) > 0
