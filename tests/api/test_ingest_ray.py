"""`geoloc ingest SOURCE --ray local` as a user runs it: a manifest and a folder encoded on a real local Ray
instance give the same references and the same codes as the local path, all indexed."""

import shutil
import sqlite3

import numpy as np
import pytest

from tests.api.test_ingest import GPS_PHOTOS, ingest
from tests.conftest import PENN

pytestmark = [pytest.mark.ray, pytest.mark.slow]


def stored(data) -> dict[str, tuple]:
    db = sqlite3.connect(data / "references.sqlite")
    try:
        rows = db.execute("SELECT sha256, lat, lon, label, status, float_code, binary_code FROM refs").fetchall()
        adds = db.execute("SELECT COUNT(*) FROM changes WHERE op='add'").fetchone()[0]
    finally:
        db.close()
    assert adds == len(rows)  # every reference reached the index exactly once
    return {r[0]: r[1:] for r in rows}


def test_manifest_and_folder_on_ray_match_the_local_path(tmp_path, fitted_models, mini_manifest):
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in GPS_PHOTOS:
        shutil.copy(PENN / "photos" / name, folder / name)
    got = {}
    for engine, extra in (("local", ()), ("ray", ("--ray", "local", "--workers", "2"))):
        data = tmp_path / engine
        ingest(mini_manifest, data, fitted_models, "--split", "query", *extra)
        out = ingest(folder, data, fitted_models, *extra).stdout
        assert f"ingested {len(GPS_PHOTOS)} new references" in out
        got[engine] = stored(data)

    local, ray = got["local"], got["ray"]
    assert len(local) == 9 + len(GPS_PHOTOS)  # 3 query captures x (photo + 2 crops), then the folder
    assert local.keys() == ray.keys()
    for sha, (lat, lon, label, status, fcode, bcode) in local.items():
        r = ray[sha]
        assert (lat, lon, label, status) == r[:4] and status == "indexed"
        assert np.allclose(np.frombuffer(fcode, np.float32), np.frombuffer(r[4], np.float32), atol=1e-5)
        bits = np.unpackbits(np.frombuffer(bcode, np.uint8) ^ np.frombuffer(r[5], np.uint8)).sum()
        assert bits <= 2  # a sign flip where a projection sits on zero, nothing more


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ingest_joins_a_running_cluster_by_auto_and_by_client_address(tmp_path, fitted_models, monkeypatch):
    """The cluster path of the README: a Ray head started apart from geoloc (`ray start --head`, with token
    authentication on, as Ray 2.60 does by default), then `--ray auto` (RAY_ADDRESS) and `--ray ray://...`
    (the Ray Client port) both encode on it. The head runs in a process group of its own, ended at the end."""
    import os
    import signal
    import subprocess
    import sys
    import tempfile
    import time
    from pathlib import Path

    gcs, client = _free_port(), _free_port()
    monkeypatch.setenv("RAY_AUTH_MODE", "token")
    monkeypatch.setenv("RAY_AUTH_TOKEN", "geoloc-test-" + "0" * 32)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    log = tmp_path / "head.log"
    short = Path(tempfile.mkdtemp(prefix="ray-", dir="/tmp"))  # Ray's socket paths must stay under 108 bytes
    head = subprocess.Popen(
        [str(Path(sys.executable).with_name("ray")), "start", "--head", "--block", f"--port={gcs}",
         f"--ray-client-server-port={client}", "--num-cpus=2", "--include-dashboard=false",
         "--node-ip-address=127.0.0.1", "--disable-usage-stats", f"--temp-dir={short}"],
        stdout=open(log, "w"), stderr=subprocess.STDOUT, start_new_session=True,  # noqa: SIM115
    )  # fmt: skip
    try:
        deadline = time.time() + 120
        while "block forever" not in log.read_text():
            assert head.poll() is None and time.time() < deadline, log.read_text()
            time.sleep(0.5)
        folder = tmp_path / "photos"
        folder.mkdir()
        for name in GPS_PHOTOS[:2]:
            shutil.copy(PENN / "photos" / name, folder / name)
        for n, address in enumerate(("auto", f"ray://127.0.0.1:{client}")):
            if address == "auto":
                monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{gcs}")
            else:
                monkeypatch.delenv("RAY_ADDRESS")
            data = tmp_path / f"data{n}"
            try:
                out = ingest(folder, data, fitted_models, "--ray", address).stdout
            except AssertionError as e:  # what the head's client servers said is the diagnosis
                logs = sorted(short.glob("session_latest/logs/ray_client_server*"))
                said = "\n".join(f"--- {f.name}:\n{f.read_text()[-3000:]}" for f in logs)
                raise AssertionError(f"{e}\n{said}") from None
            assert "ingested 2 new references" in out, out
            assert [r[3] for r in stored(data).values()] == ["indexed", "indexed"]
    finally:
        if head.poll() is None:
            os.killpg(head.pid, signal.SIGTERM)
            head.wait(timeout=60)
        shutil.rmtree(short, ignore_errors=True)


def test_a_client_session_the_head_failed_to_start_is_asked_for_again(monkeypatch):
    """The head's per-client server process dies now and then on a busy machine ("Starting Ray client server
    failed", seen once in CI); the next start succeeds, so `connect` asks again before failing with one line.
    That failure cannot be caused on demand on a real head, so ``ray.init`` raises it here."""
    ray = pytest.importorskip("ray")
    from app.ingestion.encoding import ray as engine

    said = "Initialization failure from server:\nRuntimeError: Starting Ray client server failed. See logs."
    calls = []

    def init(**kwargs):
        calls.append(kwargs["address"])
        if len(calls) < 2:
            raise ConnectionAbortedError(said)

    monkeypatch.setattr(ray, "init", init)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "cluster_resources", lambda: {"CPU": 2.0})
    monkeypatch.setattr(engine, "CLIENT_RETRY_PAUSE_S", 0.0)
    assert engine.connect("ray://127.0.0.1:1") and calls == ["ray://127.0.0.1:1"] * 2

    def always(what: str):
        def init(**kwargs):
            calls.append(kwargs["address"])
            raise ConnectionAbortedError(what)

        return init

    calls.clear()
    monkeypatch.setattr(ray, "init", always(said))
    with pytest.raises(engine.RayEngineError, match="failed 3 times"):
        engine.connect("ray://127.0.0.1:1")
    assert len(calls) == engine.CLIENT_ATTEMPTS == 3

    calls.clear()  # a refused connection or a wrong token is not asked for again
    monkeypatch.setattr(ray, "init", always("Initialization failure from server:\nbad token"))
    with pytest.raises(ConnectionAbortedError):
        engine.connect("ray://127.0.0.1:1")
    assert len(calls) == 1
