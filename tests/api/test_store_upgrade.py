"""A data dir and a PostgreSQL database made by main before schema migrations (commit 00671a8, taken from
git history and run as a user ran it: `geoloc fit`, `geoloc ingest` of real penn photos) start on this
code: migrated in place at the start (version recorded), every reference listed by the service and found
by /locate with its own photo.

Why the old code rather than a stored copy of its files: the old side then shares the machine, the
libraries and the model with the new one, and what is tested is exactly what an upgrade meets."""

from __future__ import annotations

import hashlib
import os
import shutil
import sqlite3
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from app.manifests import read_manifest
from app.storage.migrations import STEPS
from app.storage.settings import StorageSettings
from app.storage.store import ReferenceStore
from tests.api.conftest import CONFIG, Server
from tests.conftest import REPO

#: main as it was before schema migrations (the last commit of the upload hardening).
BEFORE_MIGRATIONS = "00671a861e55af2bcbd23bf0953675bc4c07c113"


@pytest.fixture(scope="module")
def old_code(tmp_path_factory) -> Path:
    """The ``app`` package as it was at ``BEFORE_MIGRATIONS``, unpacked from git history."""
    tmp = tmp_path_factory.mktemp("before-migrations")
    archive = tmp / "app.tar"
    out = subprocess.run(
        ["git", "-C", str(REPO), "archive", "--format=tar", "-o", str(archive), BEFORE_MIGRATIONS, "app"],
        capture_output=True, text=True,
    )  # fmt: skip
    if out.returncode != 0:
        pytest.fail(f"commit {BEFORE_MIGRATIONS} is not in this clone's history (a shallow clone?): {out.stderr}")
    with tarfile.open(archive) as tar:
        tar.extractall(tmp / "code", filter="data")
    return tmp / "code"


def _old_cli(code: Path, *args: str, env: dict | None = None) -> str:
    """``geoloc ARGS`` run by the old code (its ``app`` first on the path)."""
    full = {**os.environ, "PYTHONUNBUFFERED": "1", "GEOLOC_ORT_THREADS": "1", "PYTHONPATH": str(code), **(env or {})}
    out = subprocess.run(
        [sys.executable, "-m", "app.cli", *args], cwd=code, capture_output=True, text=True, timeout=900, env=full
    )
    assert out.returncode == 0, f"old geoloc {' '.join(args)}\n{out.stdout}\n{out.stderr}"
    return out.stdout


@pytest.fixture(scope="module")
def old_models(tmp_path_factory, old_code, models_dir, mini_manifest) -> Path:
    """A models dir fitted by the old code (an upgrade keeps its models dir too)."""
    models = tmp_path_factory.mktemp("old-models")
    shutil.copy(models_dir / "squeezenet1_1.onnx", models / "squeezenet1_1.onnx")
    _old_cli(old_code, "fit", "--manifest", str(mini_manifest), "--svm-bank", "none", "--models-dir", str(models),
             "--config", CONFIG)  # fmt: skip
    return models


def _old_ingest(code: Path, data: Path, models: Path, manifest: Path, env: dict | None = None) -> None:
    out = _old_cli(code, "ingest", "--manifest", str(manifest), "--split", "db", "--workers", "1", "--data-dir",
                   str(data), "--models-dir", str(models), "--config", CONFIG, env=env)  # fmt: skip
    assert "ingested 30 new references" in out, out


def _db_photos(manifest: Path) -> dict[str, bytes]:
    """sha256 -> bytes of the manifest's db photos (what the old ingest stored)."""
    photos = [r.image.read_bytes() for r in read_manifest(manifest) if r.split == "db"]
    return {hashlib.sha256(b).hexdigest(): b for b in photos}


def _serves_every_reference(data: Path, models: Path, photos: dict[str, bytes], env: dict | None = None) -> None:
    """The new code's server on the old data: every reference listed, and found by /locate with its photo."""
    with Server(data, models, extra_env=env) as s:
        listed = s.client.get("/references", params={"limit": 500}).json()
        refs = {r["sha256"]: r["id"] for r in listed["items"] if r["status"] == "indexed"}
        assert listed["total"] == len(photos) and set(refs) == set(photos)
        for sha, image in photos.items():
            r = s.client.post("/locate", files=[("image", ("q.jpg", image, "image/jpeg"))], data={"top_k": 5})
            assert r.status_code == 200, r.text
            assert refs[sha] in [c["reference_id"] for c in r.json()["candidates"]], (sha, r.json()["candidates"])


def _recorded(store: ReferenceStore) -> list[tuple[int, str]]:
    return [tuple(r) for r in store.db.execute("SELECT version, name FROM schema_versions ORDER BY version")]


def test_a_data_dir_made_by_main_is_migrated_at_start_and_serves_every_reference(
    tmp_path, old_code, old_models, mini_manifest
):
    data = tmp_path / "data"
    env = {"GEOLOC_DATABASE_URL": ""}  # SQLite, whatever the session's environment says
    _old_ingest(old_code, data, old_models, mini_manifest, env)
    with sqlite3.connect(data / "references.sqlite") as con:  # made before migrations: no version recorded
        assert not con.execute("SELECT 1 FROM sqlite_master WHERE name='schema_versions'").fetchone()
    _serves_every_reference(data, old_models, _db_photos(mini_manifest), env)
    store = ReferenceStore(data, read_only=True, backend=StorageSettings().backend(data))
    try:
        assert _recorded(store) == [(s.version, s.name) for s in STEPS] and store.count() == 30
    finally:
        store.close()


def test_a_postgres_database_made_by_main_is_migrated_at_start_and_serves_every_reference(
    tmp_path, old_code, old_models, mini_manifest, postgres_server, monkeypatch
):
    env = {"GEOLOC_DATABASE_URL": postgres_server.create_database()}
    data = tmp_path / "data"
    _old_ingest(old_code, data, old_models, mini_manifest, env)
    import psycopg

    with psycopg.connect(env["GEOLOC_DATABASE_URL"]) as con:  # made before migrations: no version recorded
        assert con.execute("SELECT to_regclass('schema_versions')").fetchone()[0] is None
        assert con.execute("SELECT COUNT(*) FROM refs").fetchone()[0] == 30
    _serves_every_reference(data, old_models, _db_photos(mini_manifest), env)
    monkeypatch.setenv("GEOLOC_DATABASE_URL", env["GEOLOC_DATABASE_URL"])
    store = ReferenceStore(data, read_only=True, backend=StorageSettings().backend(data))
    try:
        assert _recorded(store) == [(s.version, s.name) for s in STEPS] and store.count() == 30
    finally:
        store.close()
