"""Files and rows agree across processes: an upload racing a DELETE of the same image on another
server keeps its image; a DELETE whose file cannot be removed completes and queues the removal, which the
writer retries; orphans are swept by the writer and by `geoloc check --repair`; a backup holds the API key."""

from __future__ import annotations

import json
import shutil
import stat
import threading
import time
from pathlib import Path

import httpx

from app.apikey import key_path, load_or_create
from app.storage.files import sha256_of
from app.storage.store import ReferenceStore
from tests.api.conftest import Server, wait_job
from tests.conftest import PENN
from tests.storage.test_store_files import HOUR, _age, immutable
from tests.test_cli import geoloc

#: Real 224 px crops that are not in the mini collection (it holds crops 0 and 1 of its captures).
CROPS = sorted((PENN / "crops").glob("img_000*_3.jpg"))


def _post(client: httpx.Client, path: Path) -> httpx.Response:
    return client.post(
        "/references",
        files=[("image", (path.name, path.read_bytes(), "image/jpeg"))],
        data={"lat": 39.95, "lon": -75.19},
    )


def _until(condition, timeout: float = 30.0) -> bool:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if condition():
            return True
        time.sleep(0.2)
    return condition()


def test_uploads_racing_deletes_on_another_server_keep_their_image(tmp_path, fitted_models):
    """Two servers on one data dir: each round stores a photo, then posts it again to one server while the
    other deletes the stored reference. Every upload accepted as new must end indexed with its image."""
    data = tmp_path / "data"
    with Server(data, fitted_models) as a, Server(data, fitted_models) as b:
        accepted = []
        for n in range(40):
            photo = CROPS[n]
            first = _post(a.client, photo)
            assert first.status_code == 202, first.text
            stored = first.json()["reference_ids"][0]
            go = threading.Barrier(2)
            out: dict = {}

            def upload(photo=photo, out=out, go=go):
                go.wait()
                out["post"] = _post(b.client, photo)

            def delete(stored=stored, out=out, go=go):
                go.wait()
                out["delete"] = a.client.delete(f"/references/{stored}")

            threads = [threading.Thread(target=upload), threading.Thread(target=delete)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            assert out["post"].status_code == 202 and out["delete"].status_code == 200, (out["post"].text, n)
            body = out["post"].json()
            if not body["duplicates"][0]:
                accepted.append((n, body["job_id"], body["reference_ids"][0]))
        assert accepted, "no round accepted the upload as new: the race was not exercised"
        lost = []
        for n, job_id, ref in accepted:
            job = wait_job(a.client, job_id)
            image = a.client.get(f"/references/{ref}/image")
            if job["items"][0]["status"] != "indexed" or image.status_code != 200:
                lost.append((n, job["items"][0], image.json()))
        assert lost == [], f"{len(lost)} of {len(accepted)} accepted uploads lost their image: {lost}"
        assert ReferenceStore(data, read_only=True).queued_removals() == []


def test_a_delete_that_cannot_remove_the_file_completes_and_the_writer_removes_it_later(tmp_path, fitted_models):
    data = tmp_path / "data"
    with Server(data, fitted_models) as s:
        acc = _post(s.client, CROPS[0]).json()
        assert wait_job(s.client, acc["job_id"])["status"] == "done"
        ref = acc["reference_ids"][0]
        image = data / "images" / f"{sha256_of(CROPS[0].read_bytes())}.jpeg"
        with immutable(data / "images"):  # root cannot unlink there: the images folder is read-only to all
            r = s.client.delete(f"/references/{ref}")
            assert r.status_code == 200, r.text
            assert r.json() == {"deleted": ref, "image_removal": "queued"}
            assert s.client.get(f"/references/{ref}").status_code == 404  # row and codes are gone
            query = [("image", ("q.jpg", CROPS[0].read_bytes(), "image/jpeg"))]
            found = s.client.post("/locate", files=query).json()
            assert ref not in [c["reference_id"] for c in found["candidates"]]
            assert image.exists()  # the photo (with its EXIF GPS) is still there, but queued for removal
            assert ReferenceStore(data, read_only=True).queued_removals() == [image.name]
            again = s.client.delete(f"/references/{ref}")
            assert again.status_code == 404  # nothing half-done to retry from the client's side
        # Writable again: the writer process's retry removes it without anyone asking.
        assert _until(lambda: not image.exists(), 30), "the queued removal was not retried"
        assert _until(lambda: ReferenceStore(data, read_only=True).queued_removals() == [], 10)


def _plant(images: Path, src: Path, age_s: float) -> Path:
    """A real photo stored under its content name, no row naming it, ``age_s`` old."""
    path = images / f"{sha256_of(src.read_bytes())}.jpeg"
    shutil.copy(src, path)
    _age(path, age_s)
    return path


def test_the_writer_sweeps_old_orphans_and_keeps_young_ones(mini_collection, fitted_models, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    images = data / "images"
    old = _plant(images, CROPS[0], 2 * HOUR)
    young = _plant(images, CROPS[1], 60)
    tmp = images / ".killed-upload.jpeg.4242.4242.tmp"
    shutil.copy(CROPS[2], tmp)
    _age(tmp, 2 * HOUR)
    with Server(data, fitted_models) as s:
        assert _until(lambda: not old.exists() and not tmp.exists(), 30), "the writer did not sweep the orphans"
        assert young.exists()  # may be an upload whose rows are not committed yet
        assert s.client.get("/references").json()["total"] == 30  # nothing stored was touched
        listed = s.client.get("/references", params={"limit": 100}).json()["items"]
        assert all(s.client.get(f"/references/{r['id']}/image").status_code == 200 for r in listed[:5])


def test_check_repair_removes_orphans_and_queued_removals(mini_collection, fitted_models, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    models = ["--data-dir", str(data), "--models-dir", str(fitted_models)]
    images = data / "images"
    # A kill -9 mid-upload: image files written, rows never committed, and a temporary file.
    planted = [_plant(images, c, 2 * HOUR) for c in CROPS[:4]]
    tmp = images / ".abc.jpeg.99.99.tmp"
    shutil.copy(CROPS[4], tmp)
    _age(tmp, 2 * HOUR)
    # A delete while the images folder was read-only: its removal is queued.
    store = ReferenceStore(data)
    ref = store.list(limit=1)[0][0]
    removed_path = store.image_path(ref.id)
    with immutable(images):
        assert store.delete(ref.id) == "queued"
    store.close()
    bad = geoloc("check", *models, check=False)
    assert bad.returncode == 1
    assert "image files no row names" in bad.stderr and planted[0].name in bad.stderr
    assert "still to remove" in bad.stderr and "stale temporary files" in bad.stderr
    fixed = geoloc("check", "--repair", *models)
    assert "repair: removed 1 queued image files" in fixed.stdout
    assert "repair: removed 4 image files no row names" in fixed.stdout
    assert "repair: removed 1 stale temporary files" in fixed.stdout
    assert "ok: rows, images, codes and index agree" in fixed.stdout and "29 indexed" in fixed.stdout
    assert not any(p.exists() for p in [*planted, tmp, removed_path])
    # A young unnamed file may be an upload in flight: kept, and said so; --min-age 0 (services stopped).
    young = _plant(images, CROPS[5], 10)
    kept = geoloc("check", "--repair", *models, check=False)
    assert kept.returncode == 1 and young.exists() and "kept 1 unnamed files younger than 3600 s" in kept.stdout
    assert "ok:" in geoloc("check", "--repair", "--min-age", "0", *models).stdout and not young.exists()


def test_backup_holds_the_api_key_and_restore_puts_it_back(mini_collection, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(mini_collection, data)
    key, _ = load_or_create(data)
    backup = tmp_path / "backup"
    out = geoloc("backup", str(backup), "--data-dir", str(data))
    assert "this backup holds the API key" in out.stdout
    assert key_path(backup).read_text().strip() == key
    assert stat.S_IMODE(key_path(backup).stat().st_mode) == 0o600
    summary = json.loads((backup / "backup.json").read_text())
    assert summary["api_key"] is True and "holds the API key" in summary["note"]
    restored = tmp_path / "restored"
    geoloc("restore", str(backup), "--data-dir", str(restored))
    assert key_path(restored).read_text().strip() == key
    assert stat.S_IMODE(key_path(restored).stat().st_mode) == 0o600
