"""RootSIFT and ORB on real photos: caps, normalisation, and repeatability under a rotation."""

import cv2
import numpy as np

from app.engine.imageio import load_image
from app.engine.local_features import Orb, RootSift, root_sift
from tests.conftest import penn_photo


def _photo():
    return load_image(penn_photo("img_00000.jpg").read_bytes()).rgb


def test_rootsift_is_unit_length_and_capped():
    f = RootSift(max_keypoints=300, long_side=480)(_photo())
    assert 100 < len(f) <= 300
    assert f.descriptors.shape[1] == 128
    assert np.allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-4)
    assert (f.xy >= 0).all() and (f.xy <= 1).all()


def test_root_sift_is_the_hellinger_map():
    d = np.array([[4, 0, 0, 12]], np.float32)
    assert np.allclose(root_sift(d), [[0.5, 0, 0, np.sqrt(0.75)]])


def test_orb_bits_unpack_the_packed_descriptor():
    f = Orb(max_keypoints=200)(_photo())
    assert 50 < len(f) <= 200
    assert set(np.unique(f.descriptors)) <= {0.0, 1.0}
    assert np.array_equal(np.packbits(f.descriptors.astype(np.uint8), axis=1), f.raw)


def test_features_survive_a_rotation():
    """Most RootSIFT features of a photo find their match in the photo turned by 90 degrees."""
    rgb = _photo()
    a = RootSift(max_keypoints=500)(rgb)
    b = RootSift(max_keypoints=500)(np.ascontiguousarray(np.rot90(rgb)))
    matcher = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True)
    matches = matcher.match(a.descriptors, b.descriptors)
    good = [m for m in matches if m.distance < 0.5]
    assert len(good) > 0.3 * len(a)


def test_blank_image_gives_no_features():
    blank = np.full((200, 300, 3), 128, np.uint8)
    for extractor in (RootSift(), Orb()):
        f = extractor(blank)
        assert len(f) == 0 and f.descriptors.shape[0] == 0
