"""A reference's thumbnail: made once per reference and size, under the decode budget, then served from
its file.

Why: the thumbnail route is public, and it decoded the stored image on every request. Pillow scales a JPEG
while decoding it, but a 7000 x 7000 WebP was decoded whole each time: one request cost +0.94 GB, eight at
once passed 6 GB (issue 30). It is now decoded like an upload (``load_image``: reduced right after the
decode, full-size decodes sharing the process's pixel budget), once; the JPEG is kept beside the images
(``app.storage.files.THUMBNAILS``) and removed with its image.
"""

from __future__ import annotations

import io
import logging
import threading
from pathlib import Path

from PIL import Image

from app.engine.imageio import ImageLimits, load_image
from app.permissions import private_dir
from app.runtime import release_free_memory
from app.storage.files import THUMBNAILS, write_image_file

log = logging.getLogger("geoloc.thumbnails")
#: One maker per thumbnail file at a time: concurrent first requests for the same reference wait for the
#: first one's file instead of each decoding the image.
_MAKING: dict[Path, threading.Lock] = {}
_MAKING_LOCK = threading.Lock()


def thumbnail_path(image: Path, size: int) -> Path:
    return image.parent / THUMBNAILS / str(size) / f"{image.name.split('.', 1)[0]}.jpg"


def thumbnail(image: Path, size: int, limits: ImageLimits) -> bytes:
    """The JPEG thumbnail (long side ``size``) of a stored image: pixels only, no EXIF, XMP, ICC or comment.
    Raises FileNotFoundError when the image is gone, and the decode's errors for one that cannot be read.
    The shape rule of uploads does not apply: the reference is already stored (``ImageLimits.stored``)."""
    path = thumbnail_path(image, size)
    try:
        return path.read_bytes()
    except FileNotFoundError:
        pass
    with _MAKING_LOCK:
        lock = _MAKING.setdefault(path, threading.Lock())
    try:
        with lock:
            try:
                return path.read_bytes()  # made by the request this one waited for
            except FileNotFoundError:
                data = render_thumbnail(image.read_bytes(), size, limits)
            try:
                private_dir(path.parent.parent)
                private_dir(path.parent)
                write_image_file(path, data, sync=False)  # a cache: a lost one is made again
            except OSError as e:  # a full or read-only disk costs the cache, not the answer
                log.warning("thumbnail not kept in %s: %s", path.parent, e)
            return data
    finally:
        with _MAKING_LOCK:
            if _MAKING.get(path) is lock:
                del _MAKING[path]


def render_thumbnail(data: bytes, size: int, limits: ImageLimits) -> bytes:
    """The JPEG thumbnail of image bytes, decoded under ``limits`` (reduced, under the pixel budget)."""
    img = load_image(data, limits.stored(), decode_long_side=size)
    large = max(img.original_size) > 2 * size
    pixels = Image.fromarray(img.rgb)  # a new image: none of the photo's metadata comes along
    del img
    pixels.thumbnail((size, size))
    buf = io.BytesIO()
    pixels.save(buf, "JPEG", quality=85)  # JFIF only: no EXIF/GPS, XMP, ICC, IPTC or comment
    if large:  # the decode's buffers, back to the kernel (glibc keeps them in the thread's arena)
        release_free_memory()
    return buf.getvalue()
