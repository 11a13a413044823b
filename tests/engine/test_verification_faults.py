"""Verification never fails a request: pairs on which OpenCV's USAC raises count as unverified."""

import itertools

import cv2

from app.core import verify_candidates
from app.engine import rerank
from app.engine.imageio import ImageLimits, load_image
from tests.conftest import PENN


class Photos:
    """Penn photos as a ReferenceSource for the verification step (ids index the list)."""

    def __init__(self, paths):
        self.paths = paths

    def image_bytes(self, ref_id: int) -> bytes | None:
        return self.paths[ref_id].read_bytes() if ref_id < len(self.paths) else None


def test_pairs_opencv_refuses_are_unverified_not_errors():
    paths = sorted((PENN / "photos").glob("*.jpg"))[:12]
    feats = [rerank.features_for_verification(load_image(p.read_bytes()).rgb) for p in paths]
    raising = []
    for a, b in itertools.combinations(range(len(paths)), 2):
        try:
            rerank.count_inliers(feats[a], feats[b])
        except cv2.error:
            raising.append((a, b))
    assert raising, "no pair made OpenCV raise: the regression this test guards is not exercised"
    a, b = raising[0]
    query = load_image(paths[a].read_bytes()).rgb
    out = verify_candidates(query, [b, a, 99], Photos(paths), ImageLimits())
    assert out[b] is None  # OpenCV raised: unverified
    assert out[a] is not None and out[a] > 0  # the photo against itself verifies
    assert out[99] is None  # no image
