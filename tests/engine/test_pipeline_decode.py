"""Decoding at the scale a pipeline needs (``Pipeline.decode``): JPEG draft (DCT-domain) reduction with EXIF
orientation still applied, checked on the penn photos whose pixels are stored rotated (Orientation 6); and the
same photo read the same way whatever its container (JPEG, PNG of the same pixels, the 12 MP original)."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
from PIL import Image, ImageOps

from app.engine.configs import get_config
from app.engine.imageio import decode_target, load_image
from app.engine.local_features import RootSift
from app.engine.pipeline import DECODE_OVERSAMPLE, Pipeline
from tests.conftest import PENN, penn_photo


def _upright_full(path) -> np.ndarray:
    """The plain way: decode at full size, apply EXIF orientation."""
    with Image.open(path) as img:
        return np.asarray(ImageOps.exif_transpose(img).convert("RGB"))


def test_each_configuration_asks_for_what_its_branches_read():
    assert Pipeline(get_config("sift-mbvlad")).decode_sides == (640, 0)

    class _Model:  # decode_sides needs no model: only the configuration's sizes
        dim = 512

    assert Pipeline(get_config("hybrid"), global_model=_Model()).decode_sides == (640, 448)
    assert Pipeline(get_config("squeezenet-gem"), global_model=_Model()).decode_sides == (0, 448)
    assert decode_target(1600, 1200, 640, 448) == 640
    assert decode_target(1600, 900, 640, 448) == 797  # a wide photo: the short side decides


@pytest.mark.parametrize(
    ("path", "stored", "decoded"),
    [
        (penn_photo("img_00000.jpg"), (1600, 1200), (1600, 1200)),  # below 2 x 1280: whole
        (PENN / "photos-full" / "img_00050.jpg", (4032, 3024), (2016, 1512)),  # 12 MP at 1/2
    ],
)
def test_draft_decoding_keeps_the_orientation(path, stored, decoded):
    pipe = Pipeline(get_config("sift-mbvlad"))
    data = path.read_bytes()
    with Image.open(path) as img:
        assert img.size == stored and img.getexif().get(0x0112) == 6  # pixels stored rotated
    img = pipe.decode(data)
    # Upright (portrait): the stored landscape pixels were turned, after the reduced decode.
    assert img.rgb.shape == (decoded[0], decoded[1], 3)
    assert img.original_size == stored and img.gps is not None
    full = _upright_full(path)
    assert full.shape[0] > full.shape[1]
    small = cv2.resize(full, (decoded[1], decoded[0]), interpolation=cv2.INTER_AREA)
    diff = np.abs(img.rgb.astype(np.int16) - small.astype(np.int16)).mean()
    assert diff < 4.0, diff  # the same picture (DCT scaling vs area resize differ by a few levels)
    # A decode that forgot the orientation would be far off: the picture turned the other way.
    wrong = cv2.resize(np.rot90(full, 2), (decoded[1], decoded[0]), interpolation=cv2.INTER_AREA)
    assert np.abs(img.rgb.astype(np.int16) - wrong.astype(np.int16)).mean() > 4 * diff


def test_small_images_and_the_default_decode_are_unchanged():
    """A crop below twice the target decodes as it is; ``load_image`` without a pipeline keeps its 1600 px
    target (the hardening tests check that path byte for byte)."""
    pipe = Pipeline(get_config("sift-mbvlad"))
    crop = sorted((PENN / "crops").glob("*.jpg"))[0]
    assert np.array_equal(pipe.decode(crop.read_bytes()).rgb, load_image(crop.read_bytes()).rgb)
    photo = penn_photo("img_00000.jpg").read_bytes()
    assert load_image(photo).rgb.shape == (1600, 1200, 3)


def _png_of(rgb: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return buf.getvalue()


def test_the_same_photo_is_read_the_same_whatever_its_container():
    """The demo's photo as its JPEG, as a PNG of the same pixels and as its 12 MP original was once
    decoded at three sizes by three filters (DCT 1/2, box 3, DCT 1/8) and answered with three
    confidences. Now a PNG of a JPEG's pixels reaches the branches as the very same pixels, and the original
    within a few grey levels of them, at the sizes the default configuration reads."""
    assert DECODE_OVERSAMPLE >= 2

    class _Model:  # decoding needs no model: only the configuration's sizes
        dim = 720

    pipe = Pipeline(get_config("lite2-hybrid-384"), global_model=_Model())  # reads 384 px and 336 px
    jpeg = penn_photo("img_00001.jpg").read_bytes()
    from_jpeg = pipe.decode(jpeg).rgb
    upright = _upright_full(penn_photo("img_00001.jpg"))  # the JPEG's pixels, as a PNG would carry them
    from_png = pipe.decode(_png_of(upright)).rgb
    assert np.array_equal(from_png, from_jpeg)
    sift = RootSift(long_side=384)
    a, b = sift(from_jpeg), sift(from_png)
    assert np.array_equal(a.xy, b.xy) and np.array_equal(a.descriptors, b.descriptors)
    # The 12 MP original (a different encoding of the same capture): what the local branch reads agrees.
    original = pipe.decode((PENN / "photos-full" / "img_00001.jpg").read_bytes()).rgb
    assert original.shape[0] > original.shape[1] and min(original.shape[:2]) >= 2 * 384 * 3 // 4
    g1, g2 = (
        cv2.resize(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY), (288, 384), interpolation=cv2.INTER_AREA)
        for x in (from_jpeg, original)
    )
    assert np.abs(g1.astype(np.int16) - g2.astype(np.int16)).mean() < 3.0
