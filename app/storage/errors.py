"""Which failures are the storage's own (an unwritable folder, a full disk, a read-only or locked database):
they surface as ``StorageUnavailable`` so callers answer "try again later" without losing what is stored."""

from __future__ import annotations

import errno
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager

from app.errors import StorageUnavailable

#: The raw exception types of the storage's database library: what an API maps to "storage unavailable"
#: when one escapes ``storage_guard`` (callers outside storage never import sqlite3 themselves).
STORAGE_EXCEPTIONS: tuple[type[Exception], ...] = (sqlite3.Error,)

_STORAGE_ERRNOS = {errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG, errno.EIO}


def is_storage_error(exc: BaseException) -> bool:
    if isinstance(exc, StorageUnavailable):
        return True
    if isinstance(exc, sqlite3.OperationalError):
        text = str(exc).lower()
        return any(
            s in text for s in ("readonly", "read-only", "disk", "full", "unable to open", "i/o", "locked", "busy")
        )
    if isinstance(exc, OSError):
        return exc.errno in _STORAGE_ERRNOS or isinstance(exc, NotADirectoryError | IsADirectoryError)
    return False


@contextmanager
def storage_guard(what: str) -> Iterator[None]:
    """Turn the storage's own failures into ``StorageUnavailable``; anything else passes through."""
    try:
        yield
    except (OSError, sqlite3.OperationalError, sqlite3.DatabaseError) as e:
        if isinstance(e, sqlite3.IntegrityError) or not (is_storage_error(e) or isinstance(e, sqlite3.DatabaseError)):
            raise
        raise StorageUnavailable(f"{what}: the data dir cannot be written right now ({e})") from e
