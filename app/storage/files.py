"""Image files of the data dir: named by their content's sha256, written atomically, synced before the rows
that name them are committed."""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

from app.permissions import PRIVATE_FILE

IMAGES = "images"
#: Inside the images folder: a JPEG thumbnail per reference and size (``thumbnails/<px>/<sha256>.jpg``), made
#: once (``app.ingestion.thumbnails``) and removed with the image. A dot folder: what checks and sweeps of the images
#: folder pass over.
THUMBNAILS = ".thumbnails"
#: Up to this many files a batch syncs each file; beyond, one ``syncfs`` of the images' file system.
SYNC_EACH_UP_TO = 8


def sha256_of(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def write_image_file(path: Path, data: bytes, sync: bool) -> None:
    """Write to a temporary name then rename, so a reader never sees half a file. ``sync``: flush this
    file's data now; otherwise the caller syncs the whole batch at once before committing its rows."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, PRIVATE_FILE)
    try:
        os.fchmod(fd, PRIVATE_FILE)  # the umask cannot widen it, and a stale temporary file is narrowed
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            if sync:
                os.fdatasync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def syncfs(folder: Path) -> None:
    """Flush every dirty page of the file system holding ``folder`` in one call (Linux ``syncfs``): a bulk
    batch of thousands of small files costs one flush instead of one per file."""
    import ctypes

    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.syncfs(fd) != 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err))
    except AttributeError:  # no syncfs in this libc
        os.sync()
    finally:
        os.close(fd)


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
