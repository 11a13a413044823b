"""Decode an uploaded image safely: limits first, EXIF orientation applied, EXIF GPS read.

Why so careful: uploads come from strangers. The byte limit and the pixel limit are checked before any
pixel is decoded (a 30000 x 30000 PNG header costs nothing to read, its pixels cost 2.7 GB), large JPEGs
are downscaled while decoding (libjpeg's DCT scaling) so a 12 MP phone photo never lives in memory at full
size, and phone photos store their pixels rotated, so orientation is applied before anything else sees
them.

PNG, WebP and TIFF have no reduced decoding: a 49 MP one must be decoded whole (147 MB as RGB, from a PNG
of a few tens of KB). It is reduced (a box filter, like the JPEG path's DCT scaling) straight after the
decode, before any other copy is made, and such full decodes share a process-wide pixel budget, so eight
concurrent uploads cannot hold eight of them at once.
"""

from __future__ import annotations

import io
import math
import threading
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from app.engine.errors import ImageBadShape, ImageTooLarge, ImageTooSmall, UnreadableImage, UnsupportedImageFormat

ACCEPTED_FORMATS = {"JPEG", "PNG", "WEBP", "TIFF", "MPO"}  # MPO: multi-picture JPEG some phones write
try:  # HEIC only when the optional plugin is installed
    import pillow_heif  # type: ignore

    pillow_heif.register_heif_opener()
    ACCEPTED_FORMATS |= {"HEIF", "HEIC"}
except ImportError:  # pragma: no cover - depends on the environment
    pass

#: The most a network's input may be long, in multiples of its short side: a panorama wider than 4:1 is
#: scaled so that its long side is 4 x the short side asked for (its short side is then smaller than asked;
#: ``app.engine.dense.resize_short_side``). Photos of 4:3, 16:9 and 3:1 are scaled as before; what one image
#: asks of a network is bounded (unbounded, a 49000 x 32 strip would be scaled to 514,500 x 336).
MAX_INPUT_ASPECT = 4

GPS_IFD = 0x8825
EXIF_IFD = 0x8769
DATETIME_ORIGINAL = 0x9003
OFFSET_TIME_ORIGINAL = 0x9011  # its zone, "+02:00" (EXIF 2.31)
GPS_IMG_DIRECTION = 17
GPS_PROCESSING_METHOD = 27
#: What this service writes as EXIF/XMP GPSProcessingMethod beside a position it estimated from pixels: a
#: photo carrying it holds a guess, never ground truth, wherever it is met again (another library, an ingest).
ESTIMATE_MARK = "geoloc-estimate"


@dataclass(frozen=True)
class ImageLimits:
    """Defaults admit 12 MP (and up to 50 MP) phone photos and refuse decompression bombs."""

    max_bytes: int = 30 * 1024 * 1024
    max_pixels: int = 50_000_000
    min_side: int = 32
    #: The most the long side may be of the short side. A strip of 49000 x 32 pixels (a 5 KB PNG) describes
    #: no place, and a network that scales its short side up would be asked for 173 MP of work.
    #: Phone panoramas are up to about 6:1; 360-degree ones 2:1.
    max_aspect: float = 10.0
    #: Decode-time downscale target: the long side after decoding is at least this and at most ~2x it.
    decode_long_side: int = 1600

    def stored(self) -> ImageLimits:
        """The limits of an image already stored (encoding it, its thumbnail, verifying against it): the
        shape rule is an accept-time rule, and a reference an older version accepted and indexed must not
        drop out of the index at a re-fit. What a network is asked of it is bounded all the same
        (``MAX_INPUT_ASPECT``)."""
        return replace(self, max_aspect=math.inf)


class PixelBudget:
    """A counting semaphore in pixels: decodes that must materialise a large image at full size take their
    pixel count from it and wait while it is spent. One request larger than the whole budget takes all of it."""

    def __init__(self, pixels: int):
        self.capacity = pixels
        self.free = pixels
        self._cond = threading.Condition()

    @contextmanager
    def hold(self, pixels: int):
        want = min(pixels, self.capacity)
        with self._cond:
            self._cond.wait_for(lambda: self.free >= want)
            self.free -= want
        try:
            yield
        finally:
            with self._cond:
                self.free += want
                self._cond.notify_all()


#: Full-size decodes of images with no reduced decoding (PNG, WebP, TIFF) that exceed the decode target:
#: at most 50 MP of them at once in the process (one 49 MP PNG: about 150 MB as RGB, 200 MB as RGBA).
FULL_DECODES = PixelBudget(50_000_000)
#: Modes whose pixels can be box-averaged as they are (palette indices and 16-bit modes cannot).
REDUCIBLE_MODES = {"L", "LA", "RGB", "RGBA", "RGBX", "CMYK", "YCbCr", "I", "F"}


@dataclass(frozen=True)
class LoadedImage:
    rgb: np.ndarray  # (H, W, 3) uint8, orientation applied
    format: str
    original_size: tuple[int, int]  # (width, height) as stored, before orientation and downscale
    gps: tuple[float, float] | None
    captured_at: str | None
    heading: float | None = None  # EXIF GPSImgDirection in [0, 360), when the camera wrote one
    #: True when the EXIF GPS carries ``ESTIMATE_MARK`` (then ``gps`` is None: a guess is not a position).
    gps_estimated: bool = False
    #: True when a large non-JPEG was decoded at full size, then reduced (under FULL_DECODES); its full-size
    #: buffers are freed by the time load_image returns.
    full_decode: bool = False


def sniff_format(data: bytes) -> str | None:
    """Format from the magic bytes, not from a filename or a client's content type."""
    if data[:3] == b"\xff\xd8\xff":
        return "JPEG"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "PNG"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WEBP"
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return "TIFF"
    if data[:6] in (b"GIF87a", b"GIF89a"):
        return "GIF"
    if data[4:8] == b"ftyp" and data[8:12] in (b"heic", b"heix", b"mif1", b"msf1", b"hevc", b"avif"):
        return "HEIC" if data[8:12] != b"avif" else "AVIF"
    if data[:2] == b"BM":
        return "BMP"
    return None


def decode_target(width: int, height: int, long_side: int, short_side: int = 0) -> int:
    """The long side a decode must keep so that the image's long side is at least ``long_side`` and its
    short side at least ``short_side``, or its long side ``MAX_INPUT_ASPECT`` x ``short_side`` for a
    panorama, as a network gets it (orientation does not matter: both are about the stored sides)."""
    long_, short = max(width, height), min(width, height)
    return max(long_side, min(math.ceil(short_side * long_ / max(short, 1)), MAX_INPUT_ASPECT * short_side))


def load_image(
    data: bytes,
    limits: ImageLimits | None = None,
    decode_long_side: int | None = None,
    decode_short_side: int = 0,
) -> LoadedImage:
    """Decode ``data`` into an upright RGB array, downscaled at decode time towards ``decode_long_side``
    (and, when given, keeping the short side at least ``decode_short_side``: a pipeline's CNN branch
    resizes by the short side, its local branch by the long side; ``Pipeline.decode``)."""
    limits = limits or ImageLimits()
    if len(data) == 0:
        raise UnreadableImage("the upload is empty (0 bytes)")
    if len(data) > limits.max_bytes:
        raise ImageTooLarge(f"the upload has {len(data)} bytes; the limit is {limits.max_bytes}")
    kind = sniff_format(data)
    if kind is None:
        raise UnreadableImage("the bytes are not a JPEG, PNG, WebP or TIFF image")
    if kind not in ACCEPTED_FORMATS:
        raise UnsupportedImageFormat(
            f"{kind} images are not supported; send JPEG, PNG, WebP or TIFF"
            + (" (HEIC needs the pillow-heif plugin)" if kind in ("HEIC", "AVIF") else "")
        )
    try:
        img = Image.open(io.BytesIO(data))
    except Image.DecompressionBombError as e:
        raise ImageTooLarge(
            f"the image declares too many pixels to decode safely: {e}; the limit is {limits.max_pixels} pixels"
        ) from None
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise UnreadableImage(f"cannot read the {kind} header: {e}") from None
    w, h = img.size
    if w * h > limits.max_pixels:
        raise ImageTooLarge(f"the image declares {w} x {h} = {w * h} pixels; the limit is {limits.max_pixels}")
    if min(w, h) < limits.min_side:
        raise ImageTooSmall(f"the image is {w} x {h}; each side must be at least {limits.min_side} pixels")
    if max(w, h) > limits.max_aspect * min(w, h):
        raise ImageBadShape(
            f"the image is {w} x {h}: one side is {max(w, h) / min(w, h):.0f} times the other, the limit is "
            f"{limits.max_aspect:g}; crop it to the part that shows the place"
        )
    # ``is_animated``, never ``n_frames``: counting a TIFF's frames walks its whole IFD chain (a crafted file of
    # a few hundred thousand IFDs sharing one strip took minutes); whether a second frame exists is known from
    # the first IFD. A TIFF or MPO is read as its first frame, the photo.
    if img.format not in ("MPO", "TIFF") and getattr(img, "is_animated", False):
        raise UnsupportedImageFormat("animated images are not supported; send a single photo")
    gps, captured_at = read_exif_gps(img)
    heading = read_exif_heading(img)
    estimated = gps is None and gps_is_estimate(img)
    target = decode_target(w, h, decode_long_side or limits.decode_long_side, decode_short_side)
    full_decode = False
    try:
        if img.format in ("JPEG", "MPO") and max(w, h) > 2 * target:
            # DCT-domain downscale by a power of two: the full-size pixels are never materialised.
            scale = max(w, h) / target
            img.draft("RGB", (math.ceil(w / scale), math.ceil(h / scale)))
        elif max(w, h) > 2 * target:
            img, full_decode = _decode_reduced(img, max(w, h) // target), True
        img = ImageOps.exif_transpose(img)
        rgb = _to_rgb(img)
    except Image.DecompressionBombError as e:
        raise ImageTooLarge(str(e)) from None
    except (OSError, ValueError, SyntaxError) as e:
        raise UnreadableImage(f"the {kind} data is damaged or truncated: {e}") from None
    return LoadedImage(
        rgb=rgb,
        format=kind,
        original_size=(w, h),
        gps=gps,
        captured_at=captured_at,
        heading=heading,
        gps_estimated=estimated,
        full_decode=full_decode,
    )


def _decode_reduced(img: Image.Image, factor: int) -> Image.Image:
    """Decode at full size under the process's pixel budget and reduce by ``factor`` at once (the long
    side stays at least the decode target, as with JPEG's DCT scaling); only the reduced image outlives
    the budget. The EXIF block (orientation) is carried over for exif_transpose."""
    w, h = img.size
    with FULL_DECODES.hold(w * h):
        exif = img.getexif()  # reads the file's EXIF (PNG's eXIf chunk) before the full image goes
        img.load()
        if img.mode in ("P", "PA"):
            img = img.convert("RGBA" if img.mode == "PA" or "transparency" in img.info else "RGB")
        elif img.mode == "1":
            img = img.convert("L")
        elif img.mode not in REDUCIBLE_MODES:  # 16-bit grey: 32-bit integers average correctly
            img = img.convert("I")
        small = img.reduce(factor)
        img.close()
    small.info["exif"] = exif.tobytes()
    return small


def _to_rgb(img: Image.Image) -> np.ndarray:
    """Any mode (CMYK, 16-bit, grayscale, alpha, palette) to 8-bit RGB; alpha is composited on white."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img, dtype=np.float64)
        top = arr.max() or 1.0
        img = Image.fromarray(np.clip(arr * (255.0 / top), 0, 255).astype(np.uint8), "L")
    if img.mode == "F":
        arr = np.asarray(img, dtype=np.float64)
        top = arr.max() or 1.0
        img = Image.fromarray(np.clip(arr * (255.0 / top), 0, 255).astype(np.uint8), "L")
    if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
        img = img.convert("RGBA")
        background = Image.new("RGBA", img.size, (255, 255, 255, 255))
        img = Image.alpha_composite(background, img)
    rgb = np.asarray(img.convert("RGB"), dtype=np.uint8)
    return np.ascontiguousarray(rgb)


def _dms_to_deg(dms, ref) -> float:
    d, m, s = (float(v) for v in dms)
    deg = d + m / 60.0 + s / 3600.0
    return -deg if ref in ("S", "W", b"S", b"W") else deg


def gps_is_estimate(img: Image.Image) -> bool:
    """Whether the EXIF GPS block says its position was estimated by this service (``ESTIMATE_MARK`` in
    GPSProcessingMethod, which EXIF stores behind an 8-byte character-code prefix)."""
    try:
        raw = img.getexif().get_ifd(GPS_IFD).get(GPS_PROCESSING_METHOD)
    except Exception:
        return False
    if raw is None:
        return False
    text = raw.decode("latin-1") if isinstance(raw, bytes) else str(raw)
    return ESTIMATE_MARK in text


def read_exif_gps(img: Image.Image) -> tuple[tuple[float, float] | None, str | None]:
    """(lat, lon) from the EXIF GPS block, or None; and DateTimeOriginal if present, as EXIF writes it
    ("2024:09:23 16:08:20"), followed by OffsetTimeOriginal ("+02:00") when the photo has one. A position
    marked as this service's estimate (``gps_is_estimate``) is None: it is a guess, not a measurement."""
    try:
        exif = img.getexif()
    except Exception:  # a broken EXIF block must not make the photo unreadable
        return None, None
    captured_at = None
    try:
        ifd = exif.get_ifd(EXIF_IFD)
        raw = ifd.get(DATETIME_ORIGINAL)
        if raw:
            captured_at = str(raw).strip("\x00 ")
            zone = str(ifd.get(OFFSET_TIME_ORIGINAL) or "").strip("\x00 ")
            if len(zone) == 6 and zone[0] in "+-":
                captured_at += zone
    except Exception:
        captured_at = None
    try:
        gps = exif.get_ifd(GPS_IFD)
        if not gps or 2 not in gps or 4 not in gps:
            return None, captured_at
        lat = _dms_to_deg(gps[2], gps.get(1, "N"))
        lon = _dms_to_deg(gps[4], gps.get(3, "E"))
    except Exception:
        return None, captured_at
    if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90 or abs(lon) > 180:
        return None, captured_at
    if lat == 0.0 and lon == 0.0:  # "null island": cameras write zeros when they had no fix
        return None, captured_at
    if gps_is_estimate(img):
        return None, captured_at
    return (lat, lon), captured_at


def read_exif_heading(img: Image.Image) -> float | None:
    """The direction the camera faced (EXIF GPSImgDirection, degrees from true or magnetic north), or None.
    A broken or out-of-range value is None: a wrong heading is worse than none."""
    try:
        raw = img.getexif().get_ifd(GPS_IFD).get(GPS_IMG_DIRECTION)
        if raw is None:
            return None
        value = float(raw)
    except Exception:
        return None
    if not math.isfinite(value) or not 0 <= value <= 360:
        return None
    return value % 360.0
