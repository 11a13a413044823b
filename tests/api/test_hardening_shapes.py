"""Crafted uploads within the byte and pixel limits, on real servers: a 5 KB
strip of 49000 x 32 pixels used to answer 500 and then grow the server to 19.7 GB (the CNN branch scaled it
to 514,500 x 336 and kept running after the answer); the same file as a reference crash-looped the writer;
a TIFF of 100,000 IFDs held /locate for 93 s counting its frames. Each is now refused or bounded before any
pixel work, and a row no encoding finishes is quarantined instead of retried for ever."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
from PIL import Image

from app.engine.dense import resize_short_side
from app.storage.queue import QUARANTINED
from app.storage.settings import StorageSettings
from app.storage.store import NewReference, ReferenceStore
from tests.api.conftest import CONFIG, Server, wait_job
from tests.conftest import PENN
from tests.test_cli import geoloc
from tools.crafted_images import STRIPS, encoded, tiff_with_frames
from tools.process_memory import MiB, rss_bytes

PHOTO = PENN / "photos" / "img_00000.jpg"
#: Real 224 px crops the mini collection does not hold (it holds crops 0 and 1 of its captures).
CROPS = sorted((PENN / "crops").glob("img_000*_3.jpg"))


def test_strips_are_refused_on_both_routes_and_the_server_stays_small(tmp_path, fitted_models, mini_collection):
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    with Server(data, fitted_models) as s:
        assert s.client.post("/locate", files=[("image", ("q.jpg", PHOTO.read_bytes()))]).status_code == 200
        idle = rss_bytes(s.proc.pid)
        for name, make in STRIPS.items():
            body = make()
            r = s.client.post("/locate", files=[("image", ("x.img", body))])
            assert r.status_code == 422 and r.json()["error"] == "image_shape", (name, r.status_code, r.text)
            assert "times the other" in r.json()["message"], name
            r = s.client.post("/references", files=[("image", ("x.img", body))], data={"lat": 39.95, "lon": -75.19})
            assert r.status_code == 422 and r.json()["error"] == "image_shape", (name, r.status_code, r.text)
        time.sleep(2)  # work left running after an answer would show here
        assert s.client.get("/health").status_code == 200
        assert rss_bytes(s.proc.pid) - idle < 300 * MiB, (idle / MiB, rss_bytes(s.proc.pid) / MiB)
        assert s.client.get("/references", params={"status": "pending"}).status_code == 200
        assert s.client.get("/ready").json()["index_size"] == 30  # nothing was accepted


def test_a_wide_panorama_within_the_limit_is_located(tmp_path, fitted_models, mini_collection):
    """10:1 is accepted; the network sees it at most 4 times as long as its input size: what one image asks
    of a network is bounded (the strip was scaled to 514,500 x 336). Photos are scaled as before."""
    assert resize_short_side(np.zeros((32, 49000, 3), np.uint8), 336).shape[:2] == (1, 1344)
    assert resize_short_side(np.zeros((160, 1600, 3), np.uint8), 336).shape[:2] == (134, 1344)
    assert resize_short_side(np.zeros((1200, 1600, 3), np.uint8), 336).shape[:2] == (336, 448)
    assert resize_short_side(np.zeros((900, 1600, 3), np.uint8), 336).shape[:2] == (336, 597)
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    strip = Image.open(PHOTO).convert("RGB").resize((1600, 160))
    with Server(data, fitted_models) as s:
        r = s.client.post("/locate", files=[("image", ("pano.png", encoded(strip, "PNG")))])
        assert r.status_code == 200, r.text
        assert r.json()["candidates"] or r.json()["reason_code"] == "no_features"


def test_a_tiff_with_a_long_frame_chain_is_read_as_its_first_frame(tmp_path, fitted_models, mini_collection):
    """100,000 IFDs of one shared 64 x 64 strip: the frames are never counted (that walked the whole chain
    for 93 s), so the answer is the photo's, at once."""
    photo = Image.open(PHOTO).convert("RGB").resize((400, 300))
    first = encoded(photo, "TIFF")
    chained = tiff_with_frames(first, 100_000)
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    with Server(data, fitted_models) as s:
        t0 = time.perf_counter()
        r = s.client.post("/locate", files=[("image", ("chain.tif", chained))])
        elapsed = time.perf_counter() - t0
        assert r.status_code == 200, r.text
        plain = s.client.post("/locate", files=[("image", ("one.tif", first))]).json()
        assert [c["reference_id"] for c in r.json()["candidates"]] == [c["reference_id"] for c in plain["candidates"]]
        assert elapsed < 30, elapsed  # a bound far from the 93 s it took, not a timing claim


def _add_pending(data: Path, images: list[tuple[bytes, str]]) -> tuple[list[int], str]:
    """Rows stored pending by the store itself, as an older version accepted them (no check at accept), on
    the backend the test's environment names (a test is a process's entry point: it reads the settings)."""
    store = ReferenceStore(data, backend=StorageSettings().backend(data))
    try:
        items, job = store.add_many(
            [
                NewReference(image=b, ext=ext, lat=39.95, lon=-75.19, label=f"row {n}")
                for n, (b, ext) in enumerate(images)
            ],
            job=True,
        )
    finally:
        store.close()
    return [i for i, _ in items], job


def test_a_poison_row_fails_alone_and_its_batch_is_indexed(tmp_path, fitted_models, mini_collection):
    """The strip stored pending by an older version: its encoding now fails (OpenCV's resize asserts on it,
    not a decode error) and that row alone is failed with the reason; before, the whole batch was retried
    for ever, and the strip's CNN work grew the process by gigabytes each time."""
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    poison = STRIPS["49000x32 png"]()
    ids, job_id = _add_pending(data, [(CROPS[0].read_bytes(), "jpg"), (poison, "png"), (CROPS[1].read_bytes(), "jpg")])
    with Server(data, fitted_models) as s:
        job = wait_job(s.client, job_id, timeout=120)
        status = {it["reference_id"]: it for it in job["items"]}
        assert [status[i]["status"] for i in ids] == ["indexed", "failed", "indexed"], job
        assert status[ids[1]]["error"].startswith("encoding failed: ") and not status[ids[1]]["quarantined"]
        assert s.client.get("/health").status_code == 200
        assert s.client.get("/ready").json()["index_size"] == 32


def test_a_row_whose_encoding_never_finishes_is_quarantined(tmp_path, fitted_models, mini_collection):
    """A row the process died encoding (its attempts were counted and never completed, as
    ``IngestWorker.run_once`` leaves them when killed) is tried again alone, and quarantined at the limit:
    failed with its reason, listed by the jobs API and by `geoloc check`; the rows beside it are indexed."""
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    ids, job_id = _add_pending(data, [(c.read_bytes(), "jpg") for c in CROPS[:3]])
    store = ReferenceStore(data)
    try:
        for _ in range(2):  # two encodings of the first row started and never finished
            assert store.start_attempts([ids[0]], limit=2) == []
        assert store.start_attempts([ids[1]], limit=2) == []  # one for the second: tried again, alone
    finally:
        store.close()
    with Server(data, fitted_models, extra_env={"GEOLOC_ENCODE_ATTEMPTS": "2"}) as s:
        job = wait_job(s.client, job_id, timeout=120)
        items = {it["reference_id"]: it for it in job["items"]}
        assert items[ids[0]]["status"] == "failed" and items[ids[0]]["quarantined"], job
        assert items[ids[0]]["error"].startswith(f"{QUARANTINED}:")
        assert [items[i]["status"] for i in ids[1:]] == ["indexed", "indexed"]
        assert job["quarantined"] == 1 and job["failed"] == 1
        log = s.read_log()
    store = ReferenceStore(data)
    try:
        assert store.attempts(ids) == {}  # returned encodings and the quarantine leave no count behind
    finally:
        store.close()
    assert "its last encoding never finished; encoding it alone" in log
    out = geoloc("check", "--data-dir", str(data), "--models-dir", str(fitted_models), "--config", CONFIG, check=False)
    said = out.stdout + out.stderr
    assert out.returncode == 1 and "quarantined references" in said and f": {ids[0]};" in said, said
