"""The stored form of a reference's local features: real RootSIFT of penn photos survives the round trip to
within the quantisation's step, and anything that is not a whole record of this version is refused."""

import numpy as np
import pytest

from app.engine import stored_features as sf
from app.engine.imageio import load_image
from app.engine.matchers.sift_mnn import features_for_verification
from tests.conftest import penn_photo


def _pixel_size(name: str, long_side: int = 800) -> tuple[int, int]:
    h, w = load_image(penn_photo(name).read_bytes()).rgb.shape[:2]
    s = long_side / max(h, w)
    return (round(w * s), round(h * s)) if s < 1 else (w, h)


@pytest.fixture(scope="module")
def photo_features():
    name = "img_00003.jpg"
    f = features_for_verification(load_image(penn_photo(name).read_bytes()).rgb)
    return f, _pixel_size(name)


def test_rootsift_of_a_penn_photo_round_trips_within_the_quantisation_step(photo_features):
    f, (w, h) = photo_features
    assert len(f) > 500  # a real photo, not an empty record
    data = sf.encode(sf.from_pixels(f.xy, f.descriptors, w, h))
    assert len(data) == sf.stored_size(len(f), 128)
    back = sf.decode(data)
    assert (back.kind, back.width, back.height, len(back)) == ("rootsift", w, h, len(f))
    # positions: 1/65535 of a side, so under 0.01 px at 800 px
    assert np.abs(back.xy_px - f.xy).max() < 0.01
    # descriptors: half a step of 1/512; none clipped (RootSIFT's components stay under 0.5 on photos)
    assert np.abs(back.descriptors - f.descriptors).max() <= 0.5 / 512 + 1e-6
    assert sf.encode(back) == data  # the record is stable: re-encoding what was read gives the same bytes


def test_unit_learned_descriptors_round_trip_shifted():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 64)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    xy = rng.uniform(0, 640, size=(300, 2)).astype(np.float32)
    back = sf.decode(sf.encode(sf.from_pixels(xy, d, 640, 480, "xfeat")))
    assert back.kind == "xfeat" and back.desc_q.shape == (300, 64)
    assert np.abs(back.descriptors - d).max() <= 0.5 / 127.5 + 1e-6


def test_an_empty_record_round_trips():
    back = sf.decode(sf.encode(sf.from_pixels(np.zeros((0, 2)), np.zeros((0, 128)), 10, 10)))
    assert len(back) == 0 and back.descriptors.shape == (0, 128)


def test_torn_corrupt_or_foreign_bytes_are_refused(photo_features):
    f, (w, h) = photo_features
    data = sf.encode(sf.from_pixels(f.xy[:50], f.descriptors[:50], w, h))
    with pytest.raises(sf.StoredFeaturesError, match="header"):
        sf.decode(data[:10])
    with pytest.raises(sf.StoredFeaturesError, match="bytes of arrays"):
        sf.decode(data[:-1])  # a torn write
    flipped = bytearray(data)
    flipped[-7] ^= 0x01
    with pytest.raises(sf.StoredFeaturesError, match="corrupt"):
        sf.decode(bytes(flipped))
    newer = bytearray(data)
    newer[4] = sf.VERSION + 1
    with pytest.raises(sf.StoredFeaturesError, match="version"):
        sf.decode(bytes(newer))
    with pytest.raises(sf.StoredFeaturesError, match="magic"):
        sf.decode(b"\xff\xd8\xff" + data[3:])  # a JPEG's bytes where features were expected


def test_mismatched_arrays_and_sizes_are_refused():
    with pytest.raises(ValueError, match="descriptors"):
        sf.from_pixels(np.zeros((3, 2)), np.zeros((2, 128)), 100, 100)
    with pytest.raises(ValueError, match="out of range"):
        sf.from_pixels(np.zeros((1, 2)), np.zeros((1, 128)), 0, 100)
