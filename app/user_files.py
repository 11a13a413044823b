"""Reading a user's files safely: a regular file, opened once, everything read from that descriptor.

Why not ``path.read_bytes()``: a folder the service scans is the user's, and it can change while a scan
runs. A name checked when the folder was listed may be a symbolic link to another file by the time it is
read (a private photo outside the library root would then become a reference served to anyone), and a
named pipe called ``b.jpg`` blocks ``open`` for ever. So a file is opened with ``O_NONBLOCK`` (a pipe does
not wait for a writer) and, when it must stay inside a folder, ``O_NOFOLLOW`` (a link is refused); then
``fstat`` on the descriptor says whether it is a regular file, and the descriptor's own path (``/proc``)
whether it lies inside the folder, whatever its parents became. Every later read uses that descriptor."""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

_PROC_FD = Path("/proc/self/fd")


class FileTooLarge(OSError):
    """The file holds more bytes than the caller reads."""


class NotARegularFile(OSError):
    """The path is a link (where links are refused), a pipe, a device or a folder, or it lies outside the
    folder it must stay in: the message says which."""


def is_within(path: Path, folder: Path) -> bool:
    """Whether ``path`` (already resolved) is ``folder`` (resolved) or lies under it."""
    return path == folder or folder in path.parents


def real_path(fd: int, fallback: Path) -> Path:
    """Where the open file ``fd`` really is: its ``/proc`` link where the system has one (it names the file
    itself, not the path used to open it), else ``fallback`` resolved."""
    try:
        return Path(os.readlink(_PROC_FD / str(fd)))
    except OSError:
        return Path(fallback).resolve()


def open_regular(path: Path, within: Path | None = None) -> int:
    """A read-only descriptor of ``path``, which must be a regular file; with ``within`` (a resolved folder)
    also no link and inside that folder. Raises ``NotARegularFile`` (an ``OSError``) otherwise."""
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    if within is not None:
        flags |= os.O_NOFOLLOW
    try:
        fd = os.open(path, flags)
    except OSError as e:
        if within is not None and e.errno == errno.ELOOP:
            raise NotARegularFile(e.errno, "a symbolic link: not followed", str(path)) from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotARegularFile(f"{Path(path).name} is not a regular file (a pipe, device or folder)")
        if within is not None and not is_within(real_path(fd, Path(path)), within):
            raise NotARegularFile(f"{Path(path).name} lies outside {within}: not read")
    except BaseException:
        os.close(fd)
        raise
    return fd


@contextmanager
def opened(path: Path, within: Path | None = None) -> Iterator[tuple[BinaryIO, os.stat_result]]:
    """``open_regular`` as a binary file object and the ``fstat`` of what was opened."""
    fd = open_regular(path, within)
    f = os.fdopen(fd, "rb")
    with f:
        yield f, os.fstat(f.fileno())


def read_regular(path: Path, within: Path | None = None, max_bytes: int | None = None) -> bytes:
    """The bytes of ``path`` (see ``open_regular``); ``FileTooLarge`` when it holds more than ``max_bytes``
    (its size checked on the descriptor before anything is read, and again by what is read: it may grow)."""
    with opened(path, within) as (f, st):
        if max_bytes is None:
            return f.read()
        if st.st_size > max_bytes:
            raise FileTooLarge(f"the file has {st.st_size} bytes; the limit is {max_bytes}")
        data = f.read(max_bytes + 1)
        if len(data) > max_bytes:
            raise FileTooLarge(f"the file has grown past the limit of {max_bytes} bytes")
        return data
