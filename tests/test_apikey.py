"""The key file: private, URL-safe, created by exactly one of several processes racing on one data dir."""

import logging
import multiprocessing as mp
import os
import stat
import subprocess
import sys

import pytest

from app.apikey import KEY_PATTERN, ApiKeyError, key_path, load_or_create, resolve
from tests.conftest import REPO


def test_first_call_creates_a_private_url_safe_key_later_calls_read_it(tmp_path):
    key, created = load_or_create(tmp_path / "data")
    path = key_path(tmp_path / "data")
    assert created and KEY_PATTERN.fullmatch(key) and len(key) >= 32
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert path.read_text().strip() == key
    assert load_or_create(tmp_path / "data") == (key, False)
    assert [p.name for p in (tmp_path / "data").iterdir()] == ["api_key"]  # no temporary file left behind


def _race(data_dir, barrier, out):
    barrier.wait()
    out.put(load_or_create(data_dir))


def test_processes_racing_on_one_data_dir_share_one_key(tmp_path):
    ctx = mp.get_context("fork")
    n = 8
    barrier, out = ctx.Barrier(n), ctx.Queue()
    procs = [ctx.Process(target=_race, args=(tmp_path / "data", barrier, out)) for _ in range(n)]
    for p in procs:
        p.start()
    results = [out.get(timeout=30) for _ in range(n)]
    for p in procs:
        p.join(30)
    assert len({key for key, _ in results}) == 1
    assert sum(created for _, created in results) == 1
    assert key_path(tmp_path / "data").read_text().strip() == results[0][0]


@pytest.mark.parametrize("text", ["", "short", "x" * 40 + " spaces inside " + "y" * 20, "é" * 40])
def test_a_bad_key_file_stops_the_start_with_what_to_do(tmp_path, text):
    key_path(tmp_path).write_text(text)
    with pytest.raises(ApiKeyError, match="delete it"):
        load_or_create(tmp_path)


def test_precedence_env_key_then_no_auth_then_file(tmp_path, caplog):
    caplog.set_level(logging.INFO, "geoloc.auth")
    assert resolve("from-env", False, tmp_path) == "from-env"
    assert resolve("from-env", True, tmp_path) == "from-env"
    assert "wins over --no-auth" in caplog.text
    assert not key_path(tmp_path).exists()  # a key in the environment: no file is made
    assert resolve(None, True, tmp_path) is None
    assert "AUTH IS OFF" in caplog.text and not key_path(tmp_path).exists()
    caplog.clear()
    key = resolve(None, False, tmp_path)
    assert caplog.text.count(f"API key: {key}") == 1
    caplog.clear()
    assert resolve(None, False, tmp_path) == key
    assert key not in caplog.text  # logged once, when it was made


def _cli_key(data_dir, **env):
    base = {k: v for k, v in os.environ.items() if k not in ("GEOLOC_API_KEY", "GEOLOC_NO_AUTH")}
    return subprocess.run(
        [sys.executable, "-m", "app.cli", "api-key", "--data-dir", str(data_dir)],
        capture_output=True,
        text=True,
        env={**base, **env},
        cwd=REPO,
    )


def test_the_api_key_command_prints_the_key_make_run_shows(tmp_path):
    first = _cli_key(tmp_path / "data")
    assert first.returncode == 0, first.stderr
    key = first.stdout.strip()
    assert key == key_path(tmp_path / "data").read_text().strip()
    assert _cli_key(tmp_path / "data").stdout.strip() == key
    assert _cli_key(tmp_path / "data", GEOLOC_API_KEY="from-env").stdout.strip() == "from-env"
    off = _cli_key(tmp_path / "other", GEOLOC_NO_AUTH="true")
    assert off.returncode != 0 and "NO_AUTH" in off.stderr and not key_path(tmp_path / "other").exists()
