"""A real PostgreSQL server for the tests and benchmarks: Debian's binaries, ``initdb`` and ``pg_ctl`` run as the
``postgres`` user (initdb refuses root) in a temporary directory, on a free port, with its unix socket in
that directory and trust authentication on localhost. ``make test`` installs the ``postgresql`` package
where it is missing (the ``postgres`` target of the Makefile).

A run killed before its ``stop`` (kill -9 of pytest or of a benchmark) would leave its server running and
its folder behind: each server's folder records its owner (``owner``: the pid and start time of the process
that started it), and every new ``PostgresServer`` first stops the servers, and removes the folders, whose
owner is gone. A server whose owner still runs (another session's tests) is never touched."""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path


class NoPostgres(Exception):
    """Why no server can run here (the tests that need one skip with this reason)."""


def _bin_dir() -> Path:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[4]))
    if not found:
        raise NoPostgres("PostgreSQL is not installed (Debian package postgresql; `make test` installs it)")
    return Path(found[-1]).parent


#: The folders' prefix under the temporary directory, and the file naming each one's owner.
PREFIX = "geoloc-pg-"
OWNER = "owner"


def _started(pid: int) -> str | None:
    """A process's start time (clock ticks since boot, /proc/PID/stat field 22): with its pid, it names the
    process even after the pid is reused. None when there is no such process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def _owner_alive(root: Path) -> bool:
    try:
        pid, started = (root / OWNER).read_text().split()
    except (OSError, ValueError):
        return True  # not ours to judge (an older layout, or being written right now)
    return _started(int(pid)) == started


def remove_stale_servers(bin_dir: Path, as_user: list[str], tmp: Path | None = None) -> list[Path]:
    """Stop the servers (``pg_ctl stop -m immediate``) and remove the folders that runs killed before their
    ``stop`` left behind: those whose recorded owner process is gone. Returns the folders removed."""
    removed = []
    for root in sorted(Path(tmp or tempfile.gettempdir()).glob(PREFIX + "*")):
        try:  # another user's folder (a root run's is postgres's, mode 700) is not ours to judge
            if not (root / OWNER).is_file() or _owner_alive(root):
                continue
            running = (root / "data" / "postmaster.pid").exists()
        except OSError:
            continue
        if running:
            with contextlib.suppress(subprocess.TimeoutExpired):
                subprocess.run(
                    [*as_user, str(bin_dir / "pg_ctl"), "-D", str(root / "data"), "-m", "immediate", "-w", "stop"],
                    capture_output=True, timeout=60,
                )  # fmt: skip
        shutil.rmtree(root, ignore_errors=True)
        removed.append(root)
    return removed


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresServer:
    """One throw-away cluster; ``url(db)`` names a database on it, ``create_database`` makes a fresh one."""

    def __init__(self) -> None:
        self.bin = _bin_dir()
        self._as_user: list[str] = []
        pw = None
        if os.geteuid() == 0:
            try:
                pw = pwd.getpwnam("postgres")
            except KeyError as e:
                raise NoPostgres("running as root without a postgres user to run the server as") from e
            self._as_user = ["runuser", "-u", "postgres", "--"]
        remove_stale_servers(self.bin, self._as_user)
        self.root = Path(tempfile.mkdtemp(prefix=PREFIX))
        (self.root / OWNER).write_text(f"{os.getpid()} {_started(os.getpid())}\n")
        if pw is not None:
            os.chown(self.root, pw.pw_uid, pw.pw_gid)
        self.data = self.root / "data"
        self.port = _free_port()
        self.user = "postgres" if self._as_user else pwd.getpwuid(os.geteuid()).pw_name

    def _run(self, *args: str, timeout: float = 120) -> None:
        out = subprocess.run([*self._as_user, *args], capture_output=True, text=True, timeout=timeout)
        if out.returncode != 0:
            raise NoPostgres(f"{args[0]} failed: {out.stdout}{out.stderr}")

    def start(self) -> PostgresServer:
        self._run(
            str(self.bin / "initdb"), "-D", str(self.data), "-U", self.user, "--auth=trust", "-E", "UTF8",
            "--no-sync", "--locale=C",
        )  # fmt: skip
        self.start_server()
        return self

    def start_server(self) -> None:
        """Start the cluster's server (again, after ``stop_server``)."""
        opts = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=200"
        self._run(
            str(self.bin / "pg_ctl"), "-D", str(self.data), "-o", opts, "-l", str(self.root / "server.log"),
            "-w", "-t", "60", "start",
        )  # fmt: skip

    def stop_server(self) -> None:
        """Stop the server at once (as a crash would), keeping the cluster to start again."""
        self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop", timeout=60)

    def url(self, dbname: str = "postgres") -> str:
        return f"postgresql://{self.user}@127.0.0.1:{self.port}/{dbname}"

    def create_database(self) -> str:
        """A fresh, empty database; returns its URL."""
        import psycopg

        name = "t_" + uuid.uuid4().hex[:12]
        with psycopg.connect(self.url(), autocommit=True) as con:
            con.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        with contextlib.suppress(NoPostgres, subprocess.TimeoutExpired):
            self.stop_server()
        shutil.rmtree(self.root, ignore_errors=True)
