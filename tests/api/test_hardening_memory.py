"""Bounded memory for /locate: a /locate limit by default, large images that cannot be
draft-decoded reduced right after decoding under a process-wide pixel budget, and normal photos decoded
exactly as before. The memory figures themselves come from bench/locate_memory.py, not from a test."""

from __future__ import annotations

import io
import os
import threading
import time

import numpy as np
import pytest
from PIL import Image, ImageOps

from app.engine.imageio import FULL_DECODES, ImageLimits, PixelBudget, load_image
from app.settings import Settings, usable_cpus
from app.usecases.service import extraction_slots
from tests.conftest import PENN

LIMITS = ImageLimits()
#: What a decode may hold at most after it returns: the long side below twice the decode target.
MAX_LONG_SIDE = 2 * LIMITS.decode_long_side


def encode(img: Image.Image, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


def test_locate_concurrency_defaults_to_the_usable_cpus(monkeypatch, tmp_path):
    monkeypatch.delenv("GEOLOC_LOCATE_CONCURRENCY", raising=False)
    s = Settings(data_dir=tmp_path)
    assert s.locate_concurrency == usable_cpus() > 0
    assert usable_cpus() == len(os.sched_getaffinity(0))
    assert isinstance(extraction_slots(s.locate_concurrency), threading.BoundedSemaphore)
    monkeypatch.setenv("GEOLOC_LOCATE_CONCURRENCY", "0")  # still the way to turn the limit off
    assert Settings(data_dir=tmp_path).locate_concurrency == 0


@pytest.mark.parametrize("fmt", ["PNG", "JPEG", "WEBP", "TIFF"])
def test_a_49_mp_image_decodes_to_at_most_the_decode_budget(fmt):
    side = 7000  # 49 MP, under the 50 MP limit
    options = {"TIFF": {"compression": "tiff_deflate"}, "WEBP": {"lossless": True}}.get(fmt, {})
    data = encode(Image.new("RGB", (side, side), (118, 130, 141)), fmt, **options)
    img = load_image(data, LIMITS)
    h, w, _ = img.rgb.shape
    assert LIMITS.decode_long_side <= max(h, w) <= MAX_LONG_SIDE, (fmt, img.rgb.shape)
    assert img.original_size == (side, side)
    assert np.abs(img.rgb.astype(int) - (118, 130, 141)).max() <= 2  # the pixels, not a blank
    assert img.full_decode == (fmt != "JPEG")  # JPEG never materialises the full size (DCT scaling)


def test_a_reduced_png_keeps_its_orientation_and_colours():
    """EXIF orientation is applied after the reduction; palette and bilevel images are reduced as colours,
    not as averaged palette indices."""
    left_red = Image.new("RGB", (4000, 400), (255, 0, 0))
    left_red.paste((0, 0, 255), (2000, 0, 4000, 400))
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise to display
    img = load_image(encode(left_red, "PNG", exif=exif), LIMITS)
    assert img.full_decode and img.rgb.shape == (2000, 200, 3)  # reduced by 2, then rotated: portrait
    assert tuple(img.rgb[0, 100]) == (255, 0, 0) and tuple(img.rgb[-1, 100]) == (0, 0, 255)

    palette = load_image(encode(left_red.quantize(4), "PNG"), LIMITS)
    assert palette.rgb.shape == (200, 2000, 3)
    assert tuple(palette.rgb[100, 10]) == (255, 0, 0) and tuple(palette.rgb[100, -10]) == (0, 0, 255)

    grey16 = Image.fromarray(np.full((400, 4000), 40000, np.uint16))
    assert load_image(encode(grey16, "PNG"), LIMITS).rgb.shape == (200, 2000, 3)


@pytest.mark.parametrize("name", ["img_00000.jpg", "img_00002.jpg", "img_00033.jpg", "img_00010.jpg"])
def test_normal_photos_decode_exactly_as_before(name):
    """1600 px penn photos (JPEG, and the same pixels as PNG) decode byte for byte as the plain decode that
    load_image did before the change: no reduction below twice the decode target."""
    data = (PENN / "photos" / name).read_bytes()
    plain = np.asarray(ImageOps.exif_transpose(Image.open(io.BytesIO(data))).convert("RGB"))
    img = load_image(data, LIMITS)
    assert not img.full_decode and np.array_equal(img.rgb, plain)
    png = load_image(encode(Image.fromarray(plain), "PNG"), LIMITS)
    assert not png.full_decode and np.array_equal(png.rgb, plain)


def test_full_decodes_share_the_pixel_budget():
    """Holders never exceed the budget together; one request above the budget takes all of it."""
    budget = PixelBudget(100)
    held, most = [0], [0]
    lock = threading.Lock()

    def take(pixels: int) -> None:
        with budget.hold(pixels):
            with lock:
                held[0] += min(pixels, 100)
                most[0] = max(most[0], held[0])
            time.sleep(0.02)
            with lock:
                held[0] -= min(pixels, 100)

    threads = [threading.Thread(target=take, args=(p,)) for p in (60, 60, 60, 30, 500, 10)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert most[0] <= 100 and budget.free == 100
    assert FULL_DECODES.capacity >= LIMITS.max_pixels  # one 50 MP image can always be decoded


def test_free_memory_is_handed_back_on_glibc(monkeypatch):
    from app.runtime import configure_allocator, release_free_memory
    from app.settings import Settings

    assert release_free_memory()  # glibc's malloc_trim was found and called
    monkeypatch.setenv("GEOLOC_MALLOC_TRIM", "0")
    settings = Settings()
    try:
        configure_allocator(settings.malloc_tuning, settings.malloc_trim)  # what a geoloc process does at start
        assert not release_free_memory()
    finally:
        configure_allocator(False, True)  # trimming on again for the rest of the session
