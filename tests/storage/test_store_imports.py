"""The storage is light: importing it loads none of the engine's heavy libraries (a tool that only reads
rows, `geoloc check`, a worker's start, pays for none of them), and its backend comes from the settings."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from app.errors import ENGINE_CODES, code_of
from app.storage.postgres import PostgresBackend
from app.storage.settings import StorageSettings
from app.storage.sqlite import SqliteBackend
from app.storage.store import ReferenceStore

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("faiss", "onnxruntime", "cv2", "sklearn")


def test_importing_the_store_loads_no_heavy_library():
    """In a fresh interpreter (this one has loaded them all through other tests)."""
    code = (
        "import json, sys; import app.storage.store, app.storage.database, app.storage.migrations; "
        f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_every_engine_error_named_for_a_code_is_a_class_that_maps_to_it():
    """The codes are keyed by qualified name (the classes' modules are heavy): a renamed or moved class
    would silently answer internal_error, so each name must still import."""
    for name, code in ENGINE_CODES.items():
        module, _, cls_name = name.rpartition(".")
        cls = getattr(importlib.import_module(module), cls_name)
        assert isinstance(cls, type) and issubclass(cls, Exception), name
        assert code_of(cls.__new__(cls)) == code, name


def test_the_backend_is_chosen_by_the_settings(tmp_path, monkeypatch):
    monkeypatch.delenv("GEOLOC_DATABASE_URL", raising=False)
    assert isinstance(StorageSettings().backend(tmp_path), SqliteBackend)
    assert StorageSettings().backend(tmp_path).images_dir == tmp_path / "images"
    settings = StorageSettings(database_url="postgresql://u@h:5432/d", images_dir=tmp_path / "shared")
    pg = settings.backend(tmp_path)
    assert isinstance(pg, PostgresBackend)
    assert (pg.images_dir, pg.snapshots_dir) == (tmp_path / "shared", tmp_path)
    monkeypatch.setenv("GEOLOC_DATABASE_URL", " ")  # blank: unset, as always
    assert isinstance(StorageSettings().backend(tmp_path), SqliteBackend)
    monkeypatch.setenv("GEOLOC_DATABASE_URL", "mysql://h/d")
    with pytest.raises(ValueError, match="postgresql://"):
        StorageSettings().backend(tmp_path)
    # Below the entry point nothing reads the environment: a store given no backend is SQLite in its dir.
    monkeypatch.setenv("GEOLOC_DATABASE_URL", "postgresql://u@h:5432/d")
    store = ReferenceStore(tmp_path)
    try:
        assert isinstance(store.backend, SqliteBackend)
    finally:
        store.close()
