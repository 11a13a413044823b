"""GEOLOC_ORT_THREADS and GEOLOC_BUILD_CACHE are Settings fields, read once and passed down: the engine reads
no environment (its sessions take the process's count, its builds the cache dir they are given)."""

from __future__ import annotations

import pytest

from app.engine.convert.xfeat_onnx import XFEAT_WHEEL, cached_wheel
from app.engine.models import ort
from app.settings import Settings
from tests.engine.test_model_registry import write_toy_onnx


def test_settings_read_both_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("GEOLOC_ORT_THREADS", "3")
    monkeypatch.setenv("GEOLOC_BUILD_CACHE", str(tmp_path / "wheels"))
    s = Settings()
    assert s.ort_threads == 3 and s.build_cache == tmp_path / "wheels"
    monkeypatch.delenv("GEOLOC_ORT_THREADS")
    monkeypatch.delenv("GEOLOC_BUILD_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    s = Settings()
    assert s.ort_threads == 0 and s.build_cache == tmp_path / "cache" / "geoloc" / "wheels"
    monkeypatch.setenv("GEOLOC_ORT_THREADS", "-1")
    with pytest.raises(ValueError):
        Settings()


def test_sessions_take_the_process_count_unless_given_their_own(monkeypatch, tmp_path):
    path = tmp_path / "toy.onnx"
    write_toy_onnx(path)
    monkeypatch.setenv("GEOLOC_ORT_THREADS", "2")  # the environment alone changes nothing in the engine
    monkeypatch.setattr(ort, "_session_threads", 0)
    assert ort.create_session(path).get_session_options().intra_op_num_threads == 0
    ort.set_session_threads(1)
    assert ort.create_session(path).get_session_options().intra_op_num_threads == 1
    assert ort.create_session(path, intra_threads=2).get_session_options().intra_op_num_threads == 2
    with pytest.raises(ValueError):
        ort.set_session_threads(-1)


def test_geoloc_applies_the_settings_count_at_start(monkeypatch, tmp_path):
    from app import cli

    monkeypatch.setattr(ort, "_session_threads", 0)
    monkeypatch.setattr(cli, "_S", Settings(ort_threads=1))
    with pytest.raises(SystemExit) as done:
        cli.main(["models", "list", "--models-dir", str(tmp_path)])
    assert done.value.code == 0 and ort._session_threads == 1


def test_the_build_cache_is_the_folder_given(tmp_path):
    cache = tmp_path / "wheels"
    assert cached_wheel(cache) is None
    cache.mkdir()
    (cache / XFEAT_WHEEL).write_bytes(b"not the pinned wheel")
    assert cached_wheel(cache) is None  # refused: not the pinned sha256
