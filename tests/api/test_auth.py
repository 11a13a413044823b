"""The API key on a real uvicorn server: made on first start and logged once, shared by every process
on the data dir, needed for writes from loopback too; the environment's key wins; --no-auth warns."""

import stat

import httpx

from app.apikey import KEY_PATTERN, key_path
from tests.api.conftest import Server, wait_job
from tests.conftest import PENN

CROP = (PENN / "crops" / "img_00002_0.jpg").read_bytes()
REF = {"lat": 39.9522, "lon": -75.1932}


def _add(server: Server, key: str | None):
    headers = {"X-API-Key": key} if key is not None else {}
    return server.client.post("/references", files=[("image", ("a.jpg", CROP))], data=REF, headers=headers)


def _delete(server: Server, key: str | None = None):
    """A bare request: not through ``server.client``, which sends the data dir's key by itself."""
    headers = {"X-API-Key": key} if key is not None else {}
    return httpx.delete(f"{server.url}/references/999999", headers=headers, timeout=30)


def test_first_start_makes_a_key_that_every_process_on_the_data_dir_shares(tmp_path, fitted_models):
    data = tmp_path / "data"
    with Server(data, fitted_models) as first:
        path = key_path(data)
        key = path.read_text().strip()
        assert KEY_PATTERN.fullmatch(key) and len(key) >= 32
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        assert first.read_log().count(f"API key: {key}") == 1  # logged, once, by the process that made it

        # Writes need it, on loopback too; the refusal is the API's JSON.
        r = _delete(first)
        assert r.status_code == 401 and r.json()["error"] == "unauthorized", r.text
        assert _delete(first, "wrong-" + key).status_code == 401
        assert _delete(first, key).status_code == 404  # past auth: no such reference
        added = _add(first, key)
        assert added.status_code == 202, added.text
        assert wait_job(first.client, added.json()["job_id"])["status"] == "done"

        # A second API process on the same data dir, started while the first runs: the same key.
        with Server(data, fitted_models, worker="none") as second:
            assert second.api_key == key
            assert "API key:" not in second.read_log()
            assert _delete(second).status_code == 401
            assert _delete(second, key).status_code == 404
    assert key_path(data).read_text().strip() == key  # a restart changes nothing


def test_two_processes_starting_together_on_a_fresh_data_dir_agree(tmp_path, fitted_models):
    data = tmp_path / "data"
    a, b = Server(data, fitted_models), Server(data, fitted_models, worker="none")
    try:
        a.wait_ready()
        b.wait_ready()
        key = key_path(data).read_text().strip()
        assert a.api_key == b.api_key == key
        assert (a.read_log() + b.read_log()).count("API key:") == 1
        for s in (a, b):
            assert _delete(s, key).status_code == 404
    finally:
        a.stop()
        b.stop()


def test_the_environment_key_wins_over_the_file(tmp_path, fitted_models):
    data = tmp_path / "data"
    data.mkdir()
    file_key = "f" * 43
    key_path(data).write_text(file_key + "\n")
    env_key = "env-key-for-this-test"
    with Server(data, fitted_models, api_key=env_key) as s:
        assert _delete(s, file_key).status_code == 401
        assert _delete(s, env_key).status_code == 404
        assert "API key:" not in s.read_log()
    fresh = tmp_path / "fresh"
    with Server(fresh, fitted_models, api_key=env_key, worker="none") as s:
        assert _delete(s, env_key).status_code == 404
    assert not key_path(fresh).exists()  # a key in the environment: no key file is made


def test_no_auth_serves_writes_without_a_key_and_warns(tmp_path, fitted_models):
    data = tmp_path / "data"
    with Server(data, fitted_models, no_auth=True) as s:
        assert "AUTH IS OFF" in s.read_log()
        assert s.api_key is None and "X-API-Key" not in s.client.headers
        added = _add(s, None)
        assert added.status_code == 202, added.text
        assert _delete(s).status_code == 404
    assert not key_path(data).exists()
