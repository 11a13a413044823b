"""A real PostgreSQL server for the tests and benchmarks: Debian's binaries, ``initdb`` and ``pg_ctl`` run as the
``postgres`` user (initdb refuses root) in a temporary directory, on a free port, with its unix socket in
that directory and trust authentication on localhost. ``make test`` installs the ``postgresql`` package
where it is missing (the ``postgres`` target of the Makefile)."""

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


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresServer:
    """One throw-away cluster; ``url(db)`` names a database on it, ``create_database`` makes a fresh one."""

    def __init__(self) -> None:
        self.bin = _bin_dir()
        self.root = Path(tempfile.mkdtemp(prefix="geoloc-pg-"))
        self.data = self.root / "data"
        self.port = _free_port()
        self._as_user: list[str] = []
        if os.geteuid() == 0:
            try:
                pw = pwd.getpwnam("postgres")
            except KeyError as e:
                raise NoPostgres("running as root without a postgres user to run the server as") from e
            os.chown(self.root, pw.pw_uid, pw.pw_gid)
            self._as_user = ["runuser", "-u", "postgres", "--"]
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
