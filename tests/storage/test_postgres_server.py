"""The throw-away PostgreSQL server of the tests and benchmarks (``tools/postgres_server.py``): a run killed
before its ``stop`` leaves a running server and its folder behind, and the next ``PostgresServer`` stops that
server and removes the folder, while a server whose owner still runs is left alone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.conftest import REPO

STARTER = """
import sys, time
from tools.postgres_server import PostgresServer
server = PostgresServer().start()
print(server.root, flush=True)
time.sleep(600)
"""


def _postmaster_pid(root: Path) -> int:
    return int((root / "data" / "postmaster.pid").read_text().split()[0])


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat").read_text()
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_a_killed_runs_server_is_stopped_and_removed_by_the_next(postgres_server):
    """``postgres_server`` (the session's, its owner alive) must survive; the killed run's must not."""
    from tools.postgres_server import PostgresServer

    child = subprocess.Popen([sys.executable, "-c", STARTER], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        root = Path(child.stdout.readline().strip())
        assert root.is_dir(), root
        postmaster = _postmaster_pid(root)
        assert _running(postmaster)
    finally:
        child.send_signal(signal.SIGKILL)  # no stop(): the server keeps running, its folder stays
        child.wait()
    assert _running(postmaster) and root.is_dir()

    fresh = PostgresServer()  # cleans up before it makes its own folder
    try:
        deadline = time.monotonic() + 30
        while _running(postmaster):
            assert time.monotonic() < deadline, f"the stale server {postmaster} still runs"
            time.sleep(0.2)
        assert not root.exists()
        assert postgres_server.root.is_dir() and _running(_postmaster_pid(postgres_server.root))
    finally:
        fresh.stop()
