"""Verification never fails a request: pairs OpenCV's USAC refuses, images gone or undecodable, count as
unverified (None in /locate's ``inliers``) and keep their global score."""

import itertools

import cv2
import numpy as np

from app.engine.imageio import ImageLimits, load_image
from app.engine.matchers import geometry
from app.engine.matchers.sift_mnn import PixelFeatures, SiftMnnMatcher, features_for_verification
from app.usecases.locate import order_by_verification, verify_candidates
from tests.conftest import PENN


class Photos:
    """Image bytes as a ReferenceSource for the verification step (ids index the list)."""

    def __init__(self, images: list[bytes]):
        self.images = images

    def image_bytes(self, ref_id: int) -> bytes | None:
        return self.images[ref_id] if ref_id < len(self.images) else None


def test_a_fit_opencv_refuses_leaves_the_other_models_answer():
    """Positions as fractions of the image with a 0.004 threshold (what verification once used) make USAC's
    fundamental-matrix fit assert on some real penn pairs: ``fit_geometry`` must answer with the
    homography alone, not raise."""
    paths = sorted((PENN / "photos").glob("*.jpg"))[:12]
    feats: dict[int, PixelFeatures] = {}
    for a, b in itertools.combinations(range(len(paths)), 2):
        for i in (a, b):
            if i not in feats:
                feats[i] = features_for_verification(load_image(paths[i].read_bytes()).rgb)
        m = geometry.mutual_matches(feats[a].descriptors, feats[b].descriptors)
        p1, p2 = feats[a].xy[m[:, 0]] / 800, feats[b].xy[m[:, 1]] / 800
        try:
            cv2.findFundamentalMat(p1.astype(np.float64), p2.astype(np.float64), cv2.USAC_MAGSAC, 0.004, 0.999, 2000)
        except cv2.error:
            break
    else:
        raise AssertionError("no pair made OpenCV raise: the regression this test guards is not exercised")
    v = geometry.fit_geometry(p1, p2, threshold_px=0.004)
    assert v.error is None and v.model != "F" and v.f_inliers == v.h_inliers == v.inliers


def test_missing_and_undecodable_images_are_unverified_and_keep_their_place():
    photo = sorted((PENN / "photos").glob("*.jpg"))[0].read_bytes()
    query = load_image(photo).rgb
    source = Photos([b"not an image", photo])
    out = verify_candidates(query, [0, 1, 7], source, ImageLimits(), SiftMnnMatcher())
    assert out[0] is None  # undecodable
    assert out[1] is not None and out[1] > 100  # the photo against itself verifies
    assert out[7] is None  # no image
    ranked = [(7, 0.9), (0, 0.8), (1, 0.5)]
    assert [i for i, _ in order_by_verification(ranked, out)] == [1, 7, 0]  # only the verified one moves


class CountingPhotos(Photos):
    def __init__(self, images: list[bytes]):
        super().__init__(images)
        self.reads = 0

    def image_bytes(self, ref_id: int) -> bytes | None:
        self.reads += 1
        return super().image_bytes(ref_id)


def test_a_features_cache_reads_each_reference_once_and_verifies_the_same():
    """The calibration verifies hundreds of answers whose candidates recur: with a cache each reference's
    photo is read and its features computed once, and the outcomes are those of a fresh computation."""
    from app.usecases.locate import verify_candidate_pairs

    paths = sorted((PENN / "photos").glob("*.jpg"))[:4]
    query = load_image(paths[0].read_bytes()).rgb
    source = CountingPhotos([p.read_bytes() for p in paths])
    cache: dict[int, object] = {}
    first = verify_candidate_pairs(query, [1, 2, 3], source, ImageLimits(), SiftMnnMatcher(), cache)
    again = verify_candidate_pairs(query, [3, 2, 1], source, ImageLimits(), SiftMnnMatcher(), cache)
    assert source.reads == 3 and sorted(cache) == [1, 2, 3]
    fresh = verify_candidate_pairs(query, [1, 2, 3], source, ImageLimits(), SiftMnnMatcher())
    assert source.reads == 6
    for i in (1, 2, 3):
        assert (again[i].n_matches, again[i].inliers) == (first[i].n_matches, first[i].inliers)
        assert (fresh[i].n_matches, fresh[i].n_matches > 0) == (first[i].n_matches, True)
    # The calibration's cache is bounded: it forgets the oldest reference's features first.
    from app.usecases.fitting import BoundedCache

    bounded = BoundedCache(2)
    verify_candidate_pairs(query, [1, 2, 3], source, ImageLimits(), SiftMnnMatcher(), bounded)
    assert sorted(bounded) == [2, 3]
