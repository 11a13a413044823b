"""The first start of an empty data dir (GEOLOC_INITIAL_PHOTOS), as `docker compose up` runs it, without a
container: a real uvicorn server on an empty data dir and a models dir with no fitted pipeline answers
/health at once and /ready 503 with the step it is at, fits on the photos, ingests them, becomes ready and
locates; a restart neither refits nor re-ingests."""

from __future__ import annotations

import re
import shutil
import time
from pathlib import Path

import httpx
import pytest

from app.engine.configs import DEFAULT_CONFIG
from app.engine.geo import haversine_m
from app.engine.imageio import load_image
from tests.conftest import PENN
from tools.server_process import ServerProcess

CONFIG = DEFAULT_CONFIG  # what `docker compose up` fits

PHOTOS = [f"img_{n:05d}.jpg" for n in range(8)]


@pytest.fixture()
def photo_folder(tmp_path):
    folder = tmp_path / "photos" / "nested"  # a folder is read recursively
    folder.mkdir(parents=True)
    for name in PHOTOS:
        shutil.copy(PENN / "photos" / name, folder / name)
    (folder / "notes.txt").write_text("not a photo")
    return tmp_path / "photos"


@pytest.fixture()
def bare_models(tmp_path, models_dir, lite2):
    """A models dir with the built models and no fitted pipeline (what the image holds)."""
    d = tmp_path / "models"
    d.mkdir()
    for f in models_dir.glob("*.onnx"):
        shutil.copy(f, d / f.name)
    return d


def _server(data: Path, models: Path, env: dict) -> ServerProcess:
    return ServerProcess(data, models, CONFIG, extra_env={"GEOLOC_ORT_THREADS": "1", **env})


def _wait_ready(*servers: ServerProcess, timeout: float) -> list[tuple[dict, list[str]]]:
    """Poll each server's /health and /ready, turn by turn, until all are ready; per server, /ready's answer
    and every distinct 503 message it gave."""
    seen: list[list[str]] = [[] for _ in servers]
    ready: list[dict | None] = [None for _ in servers]
    deadline = time.time() + timeout
    while time.time() < deadline:
        for n, server in enumerate(servers):
            if ready[n] is not None:
                continue
            assert server.proc.poll() is None, server.read_log()
            try:
                health = server.client.get("/health")
                answer = server.client.get("/ready")
            except httpx.TransportError:
                continue
            assert health.status_code == 200, health.text  # alive during the whole first start
            if answer.status_code == 200:
                ready[n] = answer.json()
                continue
            assert answer.status_code == 503, answer.text
            body = answer.json()
            assert body["error"] == "not_ready"
            if not seen[n] or seen[n][-1] != body["message"]:
                seen[n].append(body["message"])
        if all(r is not None for r in ready):
            return list(zip(ready, seen, strict=True))
        time.sleep(0.3)
    raise TimeoutError(f"not ready after {timeout} s; /ready said {seen}\n" + "\n".join(s.read_log() for s in servers))


@pytest.mark.slow
def test_first_start_fits_ingests_and_serves(tmp_path, photo_folder, bare_models):
    """Two servers started together on one empty data dir (a scaled api service): one fits and ingests, the
    other waits for it, says so, and then serves the same generation 0: the fit and the ingest happen once."""
    data = tmp_path / "data"
    env = {"GEOLOC_INITIAL_PHOTOS": str(photo_folder)}
    server = _server(data, bare_models, env)
    twin = _server(data, bare_models, env)
    try:
        (ready, said), (twin_ready, twin_said) = _wait_ready(server, twin, timeout=900)
        assert (twin_ready["generation"], twin_ready["index_size"]) == (0, len(PHOTOS))
        logs = [Path(s.log.name).read_text() for s in (server, twin)]
        assert sum("first start done" in log for log in logs) == 1, logs  # fitted and ingested once
        assert sum("step 2 of 3" in log for log in logs) == 1, logs
        waited = [m for m in said + twin_said if "another process is fitting" in m]
        assert waited, (said, twin_said)  # the waiting one said why it was not ready
        if "first start done" in logs[1]:  # the twin won the lock: look at it from here on
            server, twin, said = twin, server, twin_said
        assert ready["config"] == CONFIG and ready["generation"] == 0
        assert ready["index_size"] == len(PHOTOS)
        # /ready said why it was not ready, step by step, in order
        steps = [m for m in said if m.startswith("first start:")]
        assert steps, said
        assert any(m.startswith("first start: fitting the pipeline: step 2 of 3") for m in steps), said
        numbers = [int(m.split("step ")[1][0]) for m in steps if "step " in m]
        assert numbers == sorted(numbers), said
        log = Path(server.log.name).read_text()
        for line in ("step 1 of 3", "step 2 of 3", "step 3 of 3", "first start done"):
            assert line in log, log  # the progress is in the log too
        # ... with the extraction's rate and each fitting step's time (to show where the first start's time goes)
        assert re.search(r"extracting features \(\d+/\d+ photos, [\d.]+ photos/s\)", log), log
        assert re.search(r"first start: fitted in codebook, PCA, binariser [\d.]+ s, .*calibration [\d.]+ s", log), log
        assert (data / "pipelines" / f"{CONFIG}-g0" / "pipeline.json").is_file()

        server.wait_ready()  # takes the key the server made in the data dir
        query = PENN / "photos" / PHOTOS[3]
        r = server.client.post("/locate", files={"image": query.read_bytes()}, data={"top_k": "3"})
        assert r.status_code == 200, r.text
        best = r.json()["candidates"][0]
        lat, lon = load_image(query.read_bytes()).gps
        assert haversine_m(lat, lon, best["lat"], best["lon"]) < 1.0  # the same photo is in the collection
    finally:
        server.stop()
        twin.stop()

    again = _server(data, bare_models, env)  # a restart: no refit, no re-ingest
    try:
        ready = again.wait_ready(timeout=300)
        assert ready["index_size"] == len(PHOTOS)
        assert "first start" not in Path(again.log.name).read_text()
    finally:
        again.stop()


def test_first_start_says_what_is_missing(tmp_path, bare_models):
    """An empty photo folder: the fit cannot start, /ready says why, and nothing is recorded in the data dir
    (adding photos and restarting is enough)."""
    from app.jobs.first_start import FirstStartError, needed, run_first_start

    photos = tmp_path / "photos"
    photos.mkdir()
    data = tmp_path / "data"
    with pytest.raises(FirstStartError, match="no photos in"):
        run_first_start(data, bare_models, CONFIG, photos, say=lambda line: None)
    assert needed(data)
    with pytest.raises(FirstStartError, match="does not exist"):
        run_first_start(data, bare_models, CONFIG, tmp_path / "missing", say=lambda line: None)


def test_a_data_dir_in_use_is_never_first_started(tmp_path):
    """A data dir bound to a pipeline (or holding references) is left alone, whatever the folder holds; one
    never opened, or opened by nothing that recorded a pipeline, gets its first start."""
    from app.jobs.first_start import needed
    from app.storage.store import ReferenceStore

    assert needed(tmp_path / "new")
    store = ReferenceStore(tmp_path / "opened")
    assert needed(tmp_path / "opened")
    store.set_meta("pipeline", f"models:{CONFIG}")
    store.close()
    assert not needed(tmp_path / "opened")
