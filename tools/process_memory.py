"""A process's resident memory from /proc, sampled: what the memory tests and benchmarks of real servers
read (psutil is not a dependency)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

MiB = 1024 * 1024


def rss_bytes(pid: int) -> int:
    """VmRSS of ``pid``."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for {pid}")


class PeakRss:
    """The largest VmRSS of ``pid`` while the ``with`` block runs, sampled every ``every_s`` (``peak``)."""

    def __init__(self, pid: int, every_s: float = 0.02):
        self.pid, self.every_s = pid, every_s
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def __enter__(self) -> PeakRss:
        self.peak = rss_bytes(self.pid)
        self._thread.start()
        return self

    def _read(self) -> None:
        try:
            self.peak = max(self.peak, rss_bytes(self.pid))
        except (OSError, RuntimeError):  # the process has ended (a command measured to its end)
            self._stop.set()

    def _sample(self) -> None:
        while not self._stop.is_set():
            self._read()
            time.sleep(self.every_s)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._read()
