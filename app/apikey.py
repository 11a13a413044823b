"""The API key that protects writes, and where it comes from.

Precedence: ``GEOLOC_API_KEY`` (the environment wins) > ``--no-auth`` / ``GEOLOC_NO_AUTH`` (auth off, said
loudly) > ``DATA_DIR/api_key``, which the first start creates. A service that anyone who reaches the port
can write to is a choice a person has to make, not a default, so a fresh data dir gets a random key.

The key file is created exclusively: the key is written to a private temporary file (``O_CREAT|O_EXCL``,
mode 0600) and published with ``link(2)``, which fails if the name exists. Of several processes starting
on one data dir (an API and its replicas, docker-compose services on one volume) exactly one creates it,
the others read the same key, and nobody ever reads a half-written file."""

from __future__ import annotations

import errno
import logging
import os
import re
import secrets
import stat
import sys
import time
from pathlib import Path

from app.permissions import private_dir

log = logging.getLogger("geoloc.auth")

KEY_FILE = "api_key"
#: URL-safe (it travels in a header and in shell lines) and long enough not to be guessed.
KEY_PATTERN = re.compile(r"[A-Za-z0-9_-]{32,}")


class ApiKeyError(RuntimeError):
    """The key file exists but holds no usable key: refuse to start rather than guess."""


def key_path(data_dir: Path) -> Path:
    return Path(data_dir) / KEY_FILE


def new_key() -> str:
    """43 URL-safe characters (256 random bits)."""
    return secrets.token_urlsafe(32)


def read_key(path: Path, wait_s: float = 5.0) -> str:
    """The key in ``path``. An empty file is only possible in the no-hard-link fallback, in the instant
    between another process's create and write: wait a little for it, then say what to do."""
    deadline = time.monotonic() + wait_s
    while True:
        text = path.read_text(encoding="ascii", errors="replace").strip()
        if text or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    if not KEY_PATTERN.fullmatch(text):
        raise ApiKeyError(
            f"{path} does not hold a URL-safe key of at least 32 characters: delete it (a new one is made at "
            "the next start) or set GEOLOC_API_KEY"
        )
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        log.warning("%s is readable by other users (mode %o): chmod 600 it", path, mode)
    return text


def _create_exclusive(path: Path, key: str) -> bool:
    """True if this call created ``path`` holding ``key``; False if it already existed."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write(key + "\n")
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)
            return True
        except FileExistsError:
            return False
        except OSError as e:
            if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
                raise
            return _create_direct(path, key)  # a file system without hard links
    finally:
        tmp.unlink(missing_ok=True)


def _create_direct(path: Path, key: str) -> bool:
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(key + "\n")
        f.flush()
        os.fsync(f.fileno())
    return True


def load_or_create(data_dir: Path) -> tuple[str, bool]:
    """The data dir's key, and whether this call created it."""
    data_dir = Path(data_dir)
    private_dir(data_dir, parents=True)
    path = key_path(data_dir)
    if not path.exists():
        key = new_key()
        if _create_exclusive(path, key):
            return key, True
    return read_key(path), False


def resolve(api_key: str | None, no_auth: bool, data_dir: Path) -> str | None:
    """The key writes need, or None when auth is off. Logs the key once, when it is created."""
    if api_key:
        if no_auth:
            log.warning("GEOLOC_API_KEY is set: it wins over --no-auth, writes need it")
        return api_key
    if no_auth:
        log.warning(
            "AUTH IS OFF (--no-auth): anyone who can reach this port can add and delete references; "
            "do this on a trusted machine only"
        )
        return None
    key, created = load_or_create(data_dir)
    if created:
        log.warning("API key: %s (stored in %s; writes need it in X-API-Key)", key, key_path(data_dir))
    else:
        log.info("writes need the API key in %s (X-API-Key header)", key_path(data_dir))
    for h in logging.getLogger().handlers + log.handlers:  # the key line must be out before anything else
        h.flush()
    sys.stderr.flush()
    return key
