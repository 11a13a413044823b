"""A reference's thumbnail: made once per reference and size, then served from its file.

Made at encoding where it can be (the encoder holds the decoded photo already: ``Encoded.thumbnail``), or on
the first request (a reference encoded before, or decoded smaller than the thumbnail), decoded like an upload
(``load_image``: reduced right after the decode, full-size decodes sharing the process's pixel budget).

Why: the thumbnail route is public, and it decoded the stored image on every request. Pillow scales a JPEG
while decoding it, but a large WebP was decoded whole each time, so a few such requests at once held
gigabytes. The JPEG is kept beside the images (``app.storage.files.THUMBNAILS``) and removed
with its image.
"""

from __future__ import annotations

import io
import logging
import threading
from pathlib import Path

import numpy as np
from PIL import Image

from app.engine.imageio import ImageLimits, load_image
from app.permissions import private_dir
from app.runtime import release_free_memory
from app.storage.files import THUMBNAILS, write_image_file

log = logging.getLogger("geoloc.thumbnails")
#: The long side of a reference's thumbnail (``GEOLOC_THUMBNAIL_PX``).
THUMBNAIL_PX = 320
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
    if not image.exists():  # a thumbnail kept for an image gone would hide what `geoloc check` reports
        raise FileNotFoundError(image)
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
            keep_thumbnail(image, size, data)
            return data
    finally:
        with _MAKING_LOCK:
            if _MAKING.get(path) is lock:
                del _MAKING[path]


def render_thumbnail(data: bytes, size: int, limits: ImageLimits) -> bytes:
    """The JPEG thumbnail of image bytes, decoded under ``limits`` (reduced, under the pixel budget)."""
    img = load_image(data, limits.stored(), decode_long_side=size)
    large = max(img.original_size) > 2 * size
    out = thumbnail_of(img.rgb, size)
    del img
    if large:  # the decode's buffers, back to the kernel (glibc keeps them in the thread's arena)
        release_free_memory()
    return out


def thumbnail_of(rgb: np.ndarray, size: int) -> bytes:
    """A JPEG of ``rgb`` (upright pixels) at most ``size`` on a side: a new image, so none of the photo's
    metadata comes along (JFIF only: no EXIF/GPS, XMP, ICC, IPTC or comment)."""
    pixels = Image.fromarray(rgb)
    pixels.thumbnail((size, size))
    buf = io.BytesIO()
    pixels.save(buf, "JPEG", quality=85)
    return buf.getvalue()


def keep_thumbnail(image: Path, size: int, data: bytes) -> Path | None:
    """Keep a thumbnail made elsewhere (at encoding: ``app.ingestion.encoding.items.encode_data``) for ``image``;
    returns its path, or None when it could not be written."""
    path = thumbnail_path(image, size)
    try:
        private_dir(path.parent.parent)
        private_dir(path.parent)
        write_image_file(path, data, sync=False)  # a cache: a lost one is made again on demand
    except OSError as e:  # a full or read-only disk costs the cache, not the encoding
        log.warning("thumbnail not kept in %s: %s", path.parent, e)
        return None
    return path
