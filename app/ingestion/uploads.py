"""Uploads, validated completely before anything is stored: decodable within the image limits, with a
position (given, or the photo's EXIF GPS), and text fields within the bounds of ``app.domain``'s
``ReferenceFields``. Every message names the image (``image n: ...``): one request may carry many."""

from __future__ import annotations

import math
from pathlib import PurePosixPath

from app.domain import Upload
from app.engine.errors import InvalidPosition, NoGpsInImage
from app.engine.geo import valid_position
from app.engine.imageio import ImageLimits, LoadedImage, load_image
from app.errors import InvalidRequest
from app.storage.store import NewReference, Reference
from app.text import CAPTURED_AT_MAX, LABEL_MAX, iso_captured_at, iso_or_as_stored, unsafe_character


def _position(u: Upload, img: LoadedImage, n: int) -> tuple[float, float]:
    if u.lat is None and u.lon is None:
        if img.gps_estimated:
            raise NoGpsInImage(
                f"image {n}: its EXIF GPS was estimated by this service from the pixels, not measured: "
                "give lat/lon to add it as a reference"
            )
        if img.gps is None:
            raise NoGpsInImage(f"image {n}: no lat/lon given and no GPS position in its EXIF")
        return img.gps
    if u.lat is None or u.lon is None:
        raise InvalidPosition(f"image {n}: give both lat and lon, or neither (to use the EXIF GPS)")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in (u.lat, u.lon)):
        raise InvalidPosition(f"image {n}: lat and lon must be numbers")  # True is not 1.0
    try:
        lat, lon = float(u.lat), float(u.lon)
    except OverflowError:  # an int of 400 digits
        raise InvalidPosition(f"image {n}: position {u.lat},{u.lon} is out of range") from None
    if not valid_position(lat, lon):
        raise InvalidPosition(f"image {n}: position {lat},{lon} is out of range (lat -90..90, lon -180..180)")
    return lat, lon


def label_from(filename: str | None) -> str | None:
    """The default label: the file's name, never a path ("../../x.jpg" -> "x.jpg"), cut to the label's length
    (a name is not something the caller typed as a label)."""
    if not filename:
        return None
    name = PurePosixPath(filename.replace("\\", "/")).name
    return name[:LABEL_MAX] or None


def _text(value, name: str, limit: int, n: int) -> str | None:
    """A text field as given (None stays None): a string, within its length, with no control character
    (``app.text``). Refused, never cut or converted: what is stored is what was asked for."""
    if value is None:
        return None
    if not isinstance(value, str):
        raise InvalidRequest(f"image {n}: {name} must be a string")
    if len(value) > limit:
        raise InvalidRequest(f"image {n}: {name} has {len(value)} characters; the limit is {limit}")
    bad = unsafe_character(value)
    if bad is not None:
        raise InvalidRequest(f"image {n}: {name} contains the control character {bad}")
    return value


def _captured_at(value, n: int) -> str | None:
    """A given capture time as ISO 8601 (``app.text.iso_captured_at``), or InvalidRequest naming the image."""
    text = _text(value, "captured_at", CAPTURED_AT_MAX, n)
    if not text:
        return None
    try:
        return iso_captured_at(text)
    except ValueError as e:
        raise InvalidRequest(f"image {n}: captured_at {e}") from None


def _exif_captured_at(value: str | None) -> str | None:
    """The photo's EXIF capture time as ISO 8601; left out when EXIF holds no usable one (the photo is fine:
    cameras write "    :  :     :  :  " for an unset clock)."""
    if not value or len(value) > CAPTURED_AT_MAX or unsafe_character(value) is not None:
        return None
    try:
        return iso_captured_at(value)
    except ValueError:
        return None


def prepare_upload(
    u: Upload, limits: ImageLimits, n: int = 0, source: str = "api", exif_heading: bool = False
) -> NewReference:
    """Validate one upload completely (decodable, within limits, with a position) before anything is stored.
    ``exif_heading``: with no heading given, take the photo's EXIF GPSImgDirection (bulk ingestion of a
    folder of photos, where EXIF is the only metadata there is)."""
    label = _text(u.label, "label", LABEL_MAX, n) or None
    captured_at = _captured_at(u.captured_at, n)
    if label is None:
        label = _text(label_from(u.filename), "file name", LABEL_MAX, n)
    img = load_image(u.data, limits)
    lat, lon = _position(u, img, n)
    hd = u.heading if u.heading is not None or not exif_heading else img.heading
    if hd is not None and (
        isinstance(hd, bool) or not (isinstance(hd, int | float) and math.isfinite(hd) and 0 <= hd < 360)
    ):
        raise InvalidRequest(f"image {n}: heading must be a number in [0, 360)")
    return NewReference(
        image=u.data,
        ext=img.format.lower(),
        lat=lat,
        lon=lon,
        heading=hd,
        captured_at=captured_at or _exif_captured_at(img.captured_at),
        label=label,
        source=source,
    )


def metadata_differences(new: NewReference, old: Reference, asked: Upload | None) -> list[str]:
    """What the upload asked for (explicitly: not a label made from the file name) that differs."""
    out = []
    if abs(new.lat - old.lat) > 1e-7 or abs(new.lon - old.lon) > 1e-7:
        out.append(f"position {old.lat:.6f},{old.lon:.6f} (not {new.lat:.6f},{new.lon:.6f})")
    for name in ("heading", "label", "captured_at"):
        value = getattr(asked, name) if asked is not None else getattr(new, name)
        stored = getattr(old, name)
        if name == "captured_at" and isinstance(value, str):  # compared as ISO 8601, as answers show them
            value, stored = iso_or_as_stored(value), iso_or_as_stored(stored)
        if value is not None and value != stored:
            out.append(f"{name} {stored!r} (not {value!r})")
    return out
