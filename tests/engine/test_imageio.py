"""Decoding: orientation, EXIF GPS, decode-time downscale, limits, odd pixel formats."""

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from app.engine.errors import ImageTooLarge, ImageTooSmall, UnreadableImage, UnsupportedImageFormat
from app.engine.imageio import ImageLimits, load_image, sniff_format
from tests.conftest import PENN


def _encode(img: Image.Image, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


def _rotated_photo() -> tuple[str, bytes]:
    """A penn photo whose EXIF Orientation is 6 (pixels stored rotated)."""
    for p in sorted((PENN / "photos").glob("*.jpg")):
        with Image.open(p) as im:
            if im.getexif().get(0x0112) == 6:
                return p.name, p.read_bytes()
    pytest.skip("no photo with orientation 6")


def test_orientation_is_applied_before_anything_else():
    _, data = _rotated_photo()
    with Image.open(io.BytesIO(data)) as im:
        stored_w, stored_h = im.size
    img = load_image(data)
    assert stored_w > stored_h  # stored landscape ...
    assert img.rgb.shape[0] > img.rgb.shape[1]  # ... shown portrait
    assert img.original_size == (stored_w, stored_h)


def test_gps_is_read_from_exif_and_matches_the_index(penn_index):
    checked = 0
    for row in penn_index:
        if not row["photo"]:
            continue
        img = load_image((PENN / row["photo"]).read_bytes())
        if img.gps is not None:
            lat, lon = img.gps
            assert lat == pytest.approx(float(row["lat"]), abs=1e-5)
            assert lon == pytest.approx(float(row["lon"]), abs=1e-5)
            checked += 1
        if checked >= 5:
            break
    assert checked >= 5


def test_crops_have_no_gps():
    img = load_image((PENN / "crops" / "img_00000_0.jpg").read_bytes())
    assert img.gps is None and img.rgb.shape == (224, 224, 3)


def test_twelve_megapixel_photo_is_downscaled_while_decoding():
    full = sorted((PENN / "photos-full").glob("*.jpg"))[0]
    img = load_image(full.read_bytes())
    assert max(img.original_size) >= 4000
    assert 1600 <= max(img.rgb.shape[:2]) <= 2 * 1600
    assert img.gps is not None


@pytest.mark.parametrize(
    "data, error",
    [
        (b"", UnreadableImage),
        (b"this is text, not a photo", UnreadableImage),
        (b"GIF89a" + b"\0" * 100, UnsupportedImageFormat),
    ],
)
def test_bad_bytes_are_refused_with_a_clear_error(data, error):
    with pytest.raises(error):
        load_image(data)


def test_truncated_jpeg_is_unreadable():
    data = (PENN / "crops" / "img_00000_0.jpg").read_bytes()
    with pytest.raises(UnreadableImage, match="damaged or truncated"):
        load_image(data[: len(data) // 3])


def _png_header_only(width: int, height: int) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


def test_decompression_bomb_is_refused_before_decoding():
    with pytest.raises(ImageTooLarge, match="pixels"):
        load_image(_png_header_only(30000, 30000))


def test_byte_limit():
    with pytest.raises(ImageTooLarge, match="bytes"):
        load_image(b"\xff\xd8\xff" + b"\0" * 2000, ImageLimits(max_bytes=1000))


def test_tiny_image_is_refused():
    with pytest.raises(ImageTooSmall):
        load_image(_encode(Image.new("RGB", (1, 1)), "PNG"))


def test_animated_gif_is_unsupported():
    frames = [Image.new("P", (64, 64), i) for i in range(3)]
    buf = io.BytesIO()
    frames[0].save(buf, "GIF", save_all=True, append_images=frames[1:])
    with pytest.raises(UnsupportedImageFormat):
        load_image(buf.getvalue())


@pytest.mark.parametrize(
    "make",
    [
        lambda: _encode(Image.new("CMYK", (80, 60), (0, 255, 0, 0)), "JPEG"),
        lambda: _encode(Image.fromarray(np.full((60, 80), 40000, np.uint16)), "PNG"),
        lambda: _encode(Image.new("L", (80, 60), 128), "PNG"),
        lambda: _encode(Image.new("RGBA", (80, 60), (255, 0, 0, 0)), "PNG"),
        lambda: _encode(Image.new("RGB", (80, 60), (0, 0, 255)), "WEBP"),
        lambda: _encode(Image.new("RGB", (80, 60), (0, 0, 255)), "TIFF"),
    ],
    ids=["cmyk-jpeg", "16bit-png", "gray-png", "alpha-png", "webp", "tiff"],
)
def test_odd_pixel_formats_become_rgb(make):
    img = load_image(make())
    assert img.rgb.dtype == np.uint8 and img.rgb.shape == (60, 80, 3)


def test_transparent_pixels_are_composited_on_white():
    img = load_image(_encode(Image.new("RGBA", (40, 40), (255, 0, 0, 0)), "PNG"))
    assert (img.rgb == 255).all()


def test_format_is_sniffed_from_bytes():
    assert sniff_format(_encode(Image.new("RGB", (8, 8)), "PNG")) == "PNG"
    assert sniff_format(b"\0\0\0\x18ftypheic" + b"\0" * 8) == "HEIC"
    assert sniff_format(b"hello") is None


def test_heading_is_read_from_exif_gps_img_direction():
    with_direction = load_image((PENN / "photos" / "img_00033.jpg").read_bytes())
    assert with_direction.heading == pytest.approx(39.2569847, abs=1e-6)
    assert load_image((PENN / "photos" / "img_00000.jpg").read_bytes()).heading is None  # no GPSImgDirection
    assert load_image((PENN / "crops" / "img_00000_0.jpg").read_bytes()).heading is None  # no EXIF at all
