"""Which failures are the storage's own (an unwritable folder, a full disk, a read-only or locked database):
they surface as ``StorageUnavailable`` so callers answer "try again later" without losing what is stored."""

from __future__ import annotations

import errno
import sqlite3
import sys
from collections.abc import Iterator
from contextlib import contextmanager

from app.errors import StorageUnavailable


def _psycopg():
    """The PostgreSQL driver when this process has loaded it (no psycopg error can occur otherwise)."""
    return sys.modules.get("psycopg")


_STORAGE_ERRNOS = {errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG, errno.EIO}


def is_storage_error(exc: BaseException) -> bool:
    if isinstance(exc, StorageUnavailable):
        return True
    if isinstance(exc, sqlite3.OperationalError):
        text = str(exc).lower()
        return any(
            s in text for s in ("readonly", "read-only", "disk", "full", "unable to open", "i/o", "locked", "busy")
        )
    pg = _psycopg()
    if pg is not None and isinstance(exc, pg.Error):
        return _postgres_unavailable(exc)
    if isinstance(exc, OSError):
        return exc.errno in _STORAGE_ERRNOS or isinstance(exc, NotADirectoryError | IsADirectoryError)
    return False


def _postgres_unavailable(exc: BaseException) -> bool:
    """The server is down or unreachable, the connection was lost, the disk is full, the database is read
    only (a standby) or refuses us: the storage's state, not a bug in a statement."""
    from psycopg import InterfaceError, OperationalError, errors

    return isinstance(
        exc,
        OperationalError
        | InterfaceError
        | errors.ReadOnlySqlTransaction
        | errors.InsufficientPrivilege
        | errors.DiskFull
        | errors.LockNotAvailable  # lock_timeout: another host holds the write lock past CONNECT_OPTIONS' bound
        | errors.QueryCanceled,
    )


@contextmanager
def storage_guard(what: str) -> Iterator[None]:
    """Turn the storage's own failures into ``StorageUnavailable``; anything else passes through."""
    try:
        yield
    except (OSError, sqlite3.OperationalError, sqlite3.DatabaseError) as e:
        if isinstance(e, sqlite3.IntegrityError) or not (is_storage_error(e) or isinstance(e, sqlite3.DatabaseError)):
            raise
        raise StorageUnavailable(f"{what}: the data dir cannot be written right now ({e})") from e
    except Exception as e:
        pg = _psycopg()
        if pg is None or not isinstance(e, pg.Error) or not _postgres_unavailable(e):
            raise
        raise StorageUnavailable(f"{what}: the database cannot be written right now ({e})") from e
