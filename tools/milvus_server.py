"""A real Milvus server for the tests: the ``milvus`` wheel's embedded Milvus standalone (its own etcd and
local storage in one process), in a temporary directory, on free ports. ``make test`` installs the wheel
(the ``milvus`` extra). ``stop`` and ``start`` again keep the data directory: the same server comes back
with what it held (the restart tests)."""

from __future__ import annotations

import shutil
import socket
import tempfile
import time
from pathlib import Path


class NoMilvus(Exception):
    """Why no server can run here (the tests that need one skip with this reason)."""


def _bind_reusing(port: int) -> socket.socket | None:
    """The wheel's check that a port is free, with SO_REUSEADDR as Milvus itself binds: without it a port the
    server just closed stays refused while its connections sit in TIME_WAIT (a minute), and a restart on the
    same port fails."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(("127.0.0.1", port))
        sock.listen()
        return sock
    except OSError:
        sock.close()
        return None


class MilvusServer:
    """One embedded Milvus standalone; ``uri`` is what ``GEOLOC_MILVUS_URI`` takes."""

    def __init__(self, root: Path | None = None):
        try:
            from milvus import MilvusServer as Embedded
            from milvus import MilvusServerConfig
        except ImportError as e:
            raise NoMilvus(f"the milvus wheel is not installed: pip install -e '.[milvus]' ({e})") from e
        self.root = Path(root or tempfile.mkdtemp(prefix="geoloc-milvus-"))
        self._owned = root is None
        config = MilvusServerConfig(data_dir=str(self.root))
        config.try_bind_port = _bind_reusing  # a restart binds its port again at once (see _bind_reusing)
        self._server = Embedded(config)
        self.port: int | None = None
        self.started_in: float | None = None

    @property
    def uri(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> MilvusServer:
        """Start (the first time on free ports; again on the same port, so clients find it where it was)."""
        if self.port is not None:
            self._server.config.configs["proxy_port"] = self.port
        t0 = time.monotonic()
        for attempt in range(30):  # a port just closed may refuse a bind for a moment
            try:
                self._server.start()
                break
            except RuntimeError as e:
                self._server.stop()
                if "bind failed" not in str(e) or attempt == 29:
                    raise NoMilvus(f"the embedded Milvus server did not start: {e} (logs: {self.root / 'logs'})") from e
                time.sleep(1.0)
            except (TimeoutError, OSError) as e:
                self._server.stop()
                raise NoMilvus(f"the embedded Milvus server did not start: {e} (logs: {self.root / 'logs'})") from e
        self.started_in = time.monotonic() - t0
        self.port = self._server.listen_port
        return self

    def stop(self) -> None:
        """Stop the process (SIGTERM, then SIGKILL after a second); the data directory stays."""
        self._server.stop()

    def remove(self) -> None:
        """Stop, and remove the data directory if this object made it."""
        self.stop()
        if self._owned:
            shutil.rmtree(self.root, ignore_errors=True)
