"""Progress of a long ingestion or fit: a tqdm bar on a terminal, one plain line per so many images otherwise.

Why two forms: a bar redrawn in place is what a person at a terminal wants, but in a log file (cron, CI,
``nohup``) it is noise, while a line every 1,000 images with the rate and the ETA is what a log needs.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import TextIO, TypeVar

from tqdm import tqdm

T = TypeVar("T")


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else f"{m}m{s:02d}s" if m else f"{s}s"


class Progress:
    """Counts images done out of ``total``; ``every``: images between two lines when not on a terminal."""

    def __init__(self, total: int, desc: str = "ingest", every: int = 1000, stream: TextIO | None = None):
        self.total = total
        self.desc = desc
        self.every = max(1, every)
        self.stream = stream or sys.stderr
        self.done = 0
        self._start = time.monotonic()
        self._next_line = self.every
        self._bar = (
            tqdm(total=total, desc=desc, unit="img", file=self.stream, dynamic_ncols=True)
            if self.stream.isatty()
            else None
        )

    def update(self, n: int) -> None:
        if n <= 0:
            return
        self.done += n
        if self._bar is not None:
            self._bar.update(n)
            return
        if self.done >= self._next_line:
            self._line()
            self._next_line = (self.done // self.every + 1) * self.every

    def line(self) -> str:
        """``ingest: 3,000/10,000 img, 41.2 img/s, ETA 2m50s``."""
        elapsed = max(time.monotonic() - self._start, 1e-9)
        rate = self.done / elapsed
        left = max(self.total - self.done, 0)
        eta = _duration(left / rate) if rate > 0 and left else "0s"
        return f"{self.desc}: {self.done:,}/{self.total:,} img, {rate:.1f} img/s, ETA {eta}"

    def _line(self) -> None:
        print(self.line(), file=self.stream, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        elif self.done % self.every:
            self._line()  # the last partial thousand


def tracked(items: Iterable[T], total: int, desc: str, stream: TextIO | None = None) -> Iterator[T]:
    """``items``, counted: a bar on a terminal, else a line with the rate every tenth of ``total`` (a fit's
    extraction and SVM labelling, which a log used to show as nothing, or as thousands of redrawn bars)."""
    progress = Progress(total, desc=desc, every=max(1, total // 10), stream=stream)
    try:
        for item in items:
            yield item
            progress.update(1)
    finally:
        progress.close()
