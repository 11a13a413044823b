"""Stored local features through operations, on penn photos: `geoloc backup` and `geoloc restore`
carry them (a restored data dir verifies at once, no back-fill), and a server started on a data dir whose
references lack them back-fills them in the background (progress on /ready, resumable, once per data dir)
while it answers."""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
import threading
import time

import pytest

from app.manifests import read_manifest
from tools.server_process import ServerProcess

CONFIG = "lite2-hybrid-384-sv"
PROFILE = "xfeat-640-n900"


@pytest.fixture(scope="module")
def sv_collection(tmp_path_factory, models_dir, mini_manifest, lite2, xfeat):
    """``lite2-hybrid-384-sv`` fitted on the mini manifest, and a data dir holding its 10 db whole photos,
    ingested by the worker (so each has its stored features). Tests copy the data dir."""
    from app.cli import fit
    from app.ingestion.worker import IngestWorker
    from app.usecases.service import GeolocService

    models = tmp_path_factory.mktemp("sv-models")
    for f in models_dir.glob("*.onnx"):
        shutil.copy(f, models / f.name)
    fit(manifest=mini_manifest, config=CONFIG, models_dir=models, seed=0, svm_bank=None, svm_bank_kind="contrastive")
    data = tmp_path_factory.mktemp("sv-collection") / "data"
    service = GeolocService.open(data, models, CONFIG)
    photos = [r for r in read_manifest(mini_manifest) if r.split == "db" and r.image.parent.name == "photos"]
    from app.domain import Upload

    service.accept([Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in photos])
    worker = IngestWorker(service, batch_size=16)
    while worker.run_once():
        pass
    assert service.store.count("indexed") == len(photos) == 10
    service.collection.write_snapshot()
    service.store.close()
    return models, data, photos


def _stored(data) -> dict[str, bytes]:
    from app.storage.feature_files import FeatureFiles, profile_root

    files = FeatureFiles(profile_root(data, PROFILE))
    return {s: files.read(s) for s in files.names()}


def _cli(*args: str) -> str:
    out = subprocess.run(
        [sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=300, env=os.environ
    )
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def test_backup_and_restore_carry_the_stored_features(sv_collection, tmp_path):
    from app.domain import LocateOptions
    from app.storage.sqlite import SqliteBackend
    from app.usecases.operations import check_data_dir
    from app.usecases.service import GeolocService

    models, data, photos = sv_collection
    original = _stored(data)
    assert len(original) == 10

    dest = tmp_path / "backup"
    out = _cli("backup", str(dest), "--data-dir", str(data))
    assert f"10 stored features ({PROFILE})" in out, out
    assert _stored(dest) == original  # the same files, the same layout
    restored = tmp_path / "restored"
    _cli("restore", str(dest), "--data-dir", str(restored))
    assert _stored(restored) == original
    report = check_data_dir(restored, models, CONFIG, SqliteBackend(restored))
    assert not any("stored features" in p for p in report.problems)

    # Verified at once from the restored files: a reference's own photo first, with many inliers.
    service = GeolocService.open(restored, models, CONFIG)
    try:
        answer = service.locate(photos[4].image.read_bytes(), LocateOptions(top_k=10))
    finally:
        service.store.close()
    first = answer.candidates[0]
    assert first.inliers is not None and first.inliers >= 100, first


def test_backfill_resumes_and_marks_the_data_dir_done(sv_collection, tmp_path):
    from app.ingestion.backfill import LOCK, MARKER, backfill_stored_features, needed
    from app.storage.feature_files import profile_root

    models, source, _ = sv_collection
    original = _stored(source)
    data = tmp_path / "data"
    shutil.copytree(source, data)
    shutil.rmtree(data / "features")  # a data dir made before its configuration stored features
    assert needed(data, None) == PROFILE

    # Stopped after 3 references (a server stopping): those files stay, the data dir is not marked done.
    stop = threading.Event()
    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        stop.set()

    first = backfill_stored_features(data, models, say=say, every=3, stop=stop)
    assert (first.total, first.seen, first.written, first.stopped) == (10, 3, 3, True), first
    assert lines[-1].endswith("(stopped: the next run resumes)") and "3/10 indexed references" in lines[0], lines
    assert len(_stored(data)) == 3 and needed(data, None) == PROFILE

    # Another process walking this data dir: a server leaves the walk to it.
    fd = os.open(profile_root(data, PROFILE) / LOCK, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        left = backfill_stored_features(data, models, say=lines.append, wait=False)
        assert left.skipped and left.seen == 0 and "left to it" in lines[-1], lines
    finally:
        os.close(fd)

    # The next run resumes: the 3 are there, the 7 others written, the same bytes ingestion wrote; done.
    second = backfill_stored_features(data, models, say=lines.append)
    assert (second.seen, second.present, second.written, second.failed) == (10, 3, 7, 0), second
    assert _stored(data) == original
    assert (profile_root(data, PROFILE) / MARKER).is_file() and needed(data, None) is None


def test_a_server_backfills_in_the_background_and_says_so_on_ready(sv_collection, tmp_path):
    models, source, photos = sv_collection
    original = _stored(source)
    data = tmp_path / "data"
    shutil.copytree(source, data)
    shutil.rmtree(data / "features")
    query = photos[4].image.read_bytes()
    env = {"GEOLOC_ORT_THREADS": "1"}

    with ServerProcess(data, models, CONFIG, extra_env=env) as server:
        # It answers while the walk goes on: candidates with a file verified, the others not (yet).
        r = server.client.post("/locate", files=[("image", ("q.jpg", query, "image/jpeg"))])
        assert r.status_code == 200, r.text
        seen: list[str] = []
        deadline = time.time() + 300
        while time.time() < deadline:
            line = server.client.get("/ready").json()["features_backfill"]
            if line and (not seen or seen[-1] != line):
                seen.append(line)
            if line and line.endswith("(done)"):
                break
            time.sleep(0.1)
        assert seen and seen[-1] == (
            f"features backfill ({PROFILE}): 10/10 indexed references, 10 written, 0 already there, 0 failed (done)"
        ), seen + [server.read_log()]
        assert _stored(data) == original
        # Now every candidate with a file is verified: its own photo first, with many inliers.
        body = server.client.post("/locate", files=[("image", ("q.jpg", query, "image/jpeg"))]).json()
        assert body["candidates"][0]["inliers"] >= 100, body["candidates"][0]

    # The next start finds the data dir done: no walk, nothing on /ready.
    with ServerProcess(data, models, CONFIG, extra_env=env) as server:
        ready = server.client.get("/ready").json()
        assert ready["status"] == "ready" and ready["features_backfill"] is None, ready
