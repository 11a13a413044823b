"""Durability of the data dir on disk, on a real server with real photos.

- A clean stop leaves every row in the SQLite main file (the WAL checkpointed), so a copy of that file
  alone holds the whole collection.
- A data dir copied without its ``-wal`` (its main file older than the index snapshot beside it) is never
  served from that snapshot: the index matches the rows, reference ids are never handed out twice, and an
  old photo is never answered with a new reference's position. ``geoloc check`` names the mismatch.
- The data dir, its database, images, snapshot and lock are private to the owner (0700 / 0600).
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import stat
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from app.storage.files import THUMBNAILS
from tests.api.conftest import CONFIG, Server, wait_job
from tests.conftest import PENN

DB = "references.sqlite"


@pytest.fixture(scope="module")
def crops(penn_index) -> list[tuple[str, bytes, float, float]]:
    """Real 224 px crops with their capture's position, one per capture so no two show the same view."""
    out = []
    for r in penn_index:
        c = r["crops"].split(";")[0]
        if c:
            out.append((c.split("/")[-1], (PENN / c).read_bytes(), float(r["lat"]), float(r["lon"])))
    return out


def _upload(client: httpx.Client, batch) -> list[int]:
    files = [("image", (name, data, "image/jpeg")) for name, data, _, _ in batch]
    meta = [{"lat": la, "lon": lo, "label": name} for name, _, la, lo in batch]
    r = client.post("/references", files=files, data={"metadata": json.dumps(meta)})
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["job_id"])
    assert job["status"] == "done", job
    return [i["reference_id"] for i in job["items"]]


def _wait_snapshot(data: Path, size: int, timeout: float = 60) -> dict:
    """The snapshot manifest once it holds ``size`` references (the writer checks every 2 s)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            m = json.loads((data / "index.json").read_text())
            if m["size"] == size:
                return m
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.2)
    raise TimeoutError(f"no snapshot of {size} references in {data}")


def _main_file_only(src: Path, dest: Path) -> None:
    """A data dir copied the way a careless backup does: everything but the database's -wal and -shm."""
    dest.mkdir(parents=True)
    for p in src.iterdir():
        if p.name.endswith(("-wal", "-shm")) or p.name == "worker.lock":
            continue
        if p.is_dir():
            shutil.copytree(p, dest / p.name)
        else:
            shutil.copy2(p, dest / p.name)


def _refs_in(db: Path) -> int:
    con = sqlite3.connect(db)
    try:
        return con.execute("SELECT COUNT(*) FROM refs").fetchone()[0]
    except sqlite3.OperationalError:  # no table: the schema itself was still in the WAL
        return 0
    finally:
        con.close()


def test_clean_stop_leaves_every_row_in_the_main_file(tmp_path, fitted_models, crops):
    data = tmp_path / "data"
    batch = crops[:12]
    with Server(data, fitted_models) as server:
        ids = _upload(server.client, batch)
        assert len(set(ids)) == len(batch)
    wal = data / f"{DB}-wal"
    assert not wal.exists() or wal.stat().st_size == 0, f"{wal.stat().st_size} bytes left in the WAL"
    copy = tmp_path / "main-only"
    copy.mkdir()
    shutil.copy2(data / DB, copy / DB)
    assert _refs_in(copy / DB) == len(batch)


@pytest.fixture(scope="module")
def copied_without_wal(tmp_path_factory, fitted_models, crops) -> dict:
    """A data dir whose main file is older than its snapshot: a reader pins the WAL (no checkpoint can pass
    it) while more uploads are indexed and snapshotted, then the server is killed and the dir copied without
    its -wal. Returns the copy and what the original served."""
    root = tmp_path_factory.mktemp("durable")
    data = root / "data"
    env = {"GEOLOC_SNAPSHOT_EVERY_CHANGES": "1"}
    first, second = crops[:6], crops[6:12]
    server = Server(data, fitted_models, extra_env=env)
    try:
        server.wait_ready()
        old_ids = _upload(server.client, first)
        pin = sqlite3.connect(data / DB, isolation_level=None)
        pin.execute("BEGIN")
        pin.execute("SELECT COUNT(*) FROM refs").fetchone()  # a read transaction: checkpoints stop here
        old_ids += _upload(server.client, second)
        manifest = _wait_snapshot(data, len(old_ids))
        # The checkpoint that follows a snapshot, if any, stops at the reader; let it end before the kill (a
        # kill in the middle of one leaves a torn main file: another story, with the same answer below).
        time.sleep(1.5)
        server.kill()  # nothing writes the main file from now on
        copy = root / "copy"
        _main_file_only(data, copy)
        pin.execute("COMMIT")
        pin.close()
    finally:
        server.stop()
    assert _refs_in(copy / DB) < len(old_ids), "the main file was not older than the snapshot"
    return {"copy": copy, "old_ids": old_ids, "old": first + second, "manifest": manifest}


def _settle(client: httpx.Client, timeout: float = 60) -> None:
    """Until no reference is pending (rows the copy holds as accepted are encoded by its worker)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        items = client.get("/references", params={"limit": 500}).json()["items"]
        if not any(i["status"] == "pending" for i in items):
            return
        time.sleep(0.2)
    raise TimeoutError("references still pending")


def test_a_copy_without_its_wal_never_serves_the_snapshot_of_lost_rows(
    tmp_path, fitted_models, crops, copied_without_wal
):
    data = tmp_path / "data"
    shutil.copytree(copied_without_wal["copy"], data)
    old_ids, old = copied_without_wal["old_ids"], copied_without_wal["old"]
    with Server(data, fitted_models) as server:
        c = server.client
        _settle(c)
        assert c.get("/ready").json()["index_size"] == c.get("/references").json()["total"]
        new = crops[20:26]
        new_ids = _upload(c, new)
        assert not set(new_ids) & set(old_ids), f"ids handed out again: {sorted(set(new_ids) & set(old_ids))}"
        assert c.get("/ready").json()["index_size"] == c.get("/references").json()["total"]
        kept = {i["id"] for i in c.get("/references", params={"limit": 500}).json()["items"]}
        for (name, image, _, _), ref_id in zip(old, old_ids, strict=True):
            if ref_id in kept:
                continue
            res = c.post("/locate", files=[("image", (name, image))], data={"top_k": 3}).json()
            for cand in res["candidates"]:
                assert not (cand["reference_id"] in new_ids and cand["score"] > 0.99), (name, cand)


def test_check_names_a_snapshot_ahead_of_its_database(tmp_path, fitted_models, copied_without_wal):
    data = tmp_path / "data"
    shutil.copytree(copied_without_wal["copy"], data)
    out = subprocess.run(
        [sys.executable, "-m", "app.cli", "check", "--data-dir", str(data), "--models-dir", str(fitted_models),
         "--config", CONFIG],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert out.returncode == 1, out.stdout + out.stderr
    assert "does not belong to this database" in out.stderr, out.stdout + out.stderr


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_the_data_dir_is_private_to_its_owner(tmp_path, fitted_models, crops):
    data = tmp_path / "data"
    old = os.umask(0o022)  # the usual umask: files the service makes itself must not depend on it
    try:
        with Server(data, fitted_models, extra_env={"GEOLOC_SNAPSHOT_EVERY_CHANGES": "1"}) as server:
            _upload(server.client, crops[:3])
            _wait_snapshot(data, 3)
            files = [data / DB, data / f"{DB}-wal", data / f"{DB}-shm", data / "worker.lock", data / "index.json"]
            images = [p for p in (data / "images").iterdir() if p.is_file()]
            thumbnails = data / "images" / THUMBNAILS  # made at encoding: a folder per size
            files += list(data.glob("*.faiss")) + images + list(thumbnails.rglob("*.jpg"))
            assert len(images) == 3 and len(list(thumbnails.rglob("*.jpg"))) == 3
            for p in files:
                assert _mode(p) == 0o600, f"{p.name}: {_mode(p):o}"
            for d in (data, data / "images", thumbnails, *(p for p in thumbnails.iterdir() if p.is_dir())):
                assert _mode(d) == 0o700, f"{d}: {_mode(d):o}"
    finally:
        os.umask(old)
