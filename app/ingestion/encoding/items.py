"""What an encoding engine takes and gives back, and the one function that turns a stored reference into
codes. Every engine (the worker's thread pool, ``geoloc ingest``, a re-index, a Ray actor) encodes through
``encode_item``, so a row gets the same codes, and the same outcome for a missing or unreadable image,
whichever engine ran it."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from app.engine.errors import GeolocError
from app.engine.imageio import ImageLimits, LoadedImage
from app.engine.pipeline import Pipeline
from app.engine.stored_features import encode as encode_stored
from app.ingestion.thumbnails import thumbnail_of

log = logging.getLogger("geoloc.encoding")


@dataclass(frozen=True)
class EncodeItem:
    """One stored reference to encode. ``data``: its image bytes when the driver read them (shipped to
    workers that share no filesystem with it); None: the worker reads ``path`` itself."""

    ref_id: int
    path: Path
    data: bytes | None = None
    #: Make the reference's thumbnail of this size from the decoded photo too (None: no thumbnail).
    thumbnail_px: int | None = None


@dataclass(frozen=True)
class Encoded:
    ref_id: int
    float_code: np.ndarray | None
    binary_code: np.ndarray | None
    error: str | None = None  # a permanent failure (the row becomes failed)
    retry: bool = False  # a storage failure: the row stays pending and is tried again later
    fingerprint: str | None = None  # the pipeline that made the codes (a re-fit may switch meanwhile)
    thumbnail: bytes | None = None  # a JPEG made from the same decode (``app.ingestion.thumbnails``), when asked
    #: The reference's stored local features (``app.engine.stored_features.encode``'s bytes) from the same
    #: decode, when the configuration names a profile (``PipelineConfig.stored_features``); the writer keeps
    #: them (``app.storage.feature_files``) before the row completes.
    stored_features: bytes | None = None


def read_item(item: EncodeItem) -> EncodeItem | Encoded:
    """The item with its bytes, or the outcome when they cannot be read: failed when the image is gone
    (its folder is there), pending when the storage itself is unreadable (tried again later)."""
    if item.data is not None:
        return item
    try:
        return replace(item, data=item.path.read_bytes())
    except FileNotFoundError:
        if item.path.parent.is_dir():
            return Encoded(item.ref_id, None, None, "the stored image is missing")
        return Encoded(item.ref_id, None, None, retry=True)
    except OSError as e:
        log.warning("reference %d: cannot read its image now (%s); it stays queued", item.ref_id, e)
        return Encoded(item.ref_id, None, None, retry=True)


def encode_data(
    pipeline: Pipeline, limits: ImageLimits, ref_id: int, data: bytes, thumbnail_px: int | None = None
) -> Encoded:
    """Image bytes to codes; a bad image is a permanent failure of that row, never an exception. So is any
    other failure while encoding it (a library's assertion on an odd image, a bug): it fails that row alone,
    with its reason, and the rest of its batch goes on (one row's ``cv2.error`` would otherwise fail its
    whole batch, which would be retried whole, for ever)."""
    try:
        img = pipeline.decode(data, limits.stored())
        codes = pipeline.encode_image(img.rgb)
        stored = _stored_features(pipeline, img)
        thumb = _thumbnail(img, thumbnail_px)
    except GeolocError as e:
        return Encoded(ref_id, None, None, str(e), fingerprint=pipeline.fingerprint)
    except MemoryError:
        raise  # the machine's state, not the image's: the row stays pending (app/ingestion/worker.py counts it)
    except Exception as e:
        log.exception("reference %d: encoding failed", ref_id)
        reason = f"encoding failed: {type(e).__name__}: {str(e)[:300]}"
        return Encoded(ref_id, None, None, reason, fingerprint=pipeline.fingerprint)
    return Encoded(
        ref_id, codes.float_, codes.binary, fingerprint=pipeline.fingerprint, thumbnail=thumb, stored_features=stored
    )


def _stored_features(pipeline: Pipeline, img: LoadedImage) -> bytes | None:
    """The stored record from the encoder's own decode (the pixels /locate's query is extracted from too:
    ``Pipeline.decode``), so a reference costs one decode whatever it stores."""
    extractor = pipeline.stored_extractor
    return None if extractor is None else encode_stored(extractor.record(img.rgb))


def _thumbnail(img: LoadedImage, size: int | None) -> bytes | None:
    """The thumbnail from the encoder's own decode, when that decode holds enough pixels for it (a photo
    is decoded at the pipeline's scale: 384 px or more for the default). Why here: a large WebP decoded
    again for its thumbnail costs a second full decode a request; the encoder has the pixels already."""
    if not size or max(img.rgb.shape[:2]) < min(size, max(img.original_size)):
        return None
    return thumbnail_of(img.rgb, size)


def encode_item(pipeline: Pipeline, limits: ImageLimits, item: EncodeItem) -> Encoded:
    """The one encode path: read the image when the item has no bytes, then encode them."""
    read = read_item(item)
    if isinstance(read, Encoded):
        return read
    return encode_data(pipeline, limits, read.ref_id, read.data, read.thumbnail_px)
