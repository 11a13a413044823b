"""Verification as pure functions: matching, the minimum before OpenCV, the H-or-F rule, the fused score."""

import cv2
import numpy as np
import pytest

from app.engine.imageio import load_image
from app.engine.rerank import MIN_MATCHES_TO_FIT, fit_geometry, fused_score, mutual_matches, verify
from tests.conftest import penn_photo


def _photo(name: str, long_side: int = 640) -> np.ndarray:
    rgb = load_image(penn_photo(name).read_bytes()).rgb
    h, w = rgb.shape[:2]
    s = long_side / max(h, w)
    return cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)


def _xfeat(model, rgb):
    out = model.detect_and_compute(rgb, top_k=2048)
    return out.keypoints, out.descriptors


def test_mutual_matches_recover_a_permutation_and_the_ratio_test_drops_twins():
    rng = np.random.default_rng(0)
    d1 = rng.normal(size=(200, 64)).astype(np.float32)
    perm = rng.permutation(200)
    d2 = d1[perm] + 0.01 * rng.normal(size=(200, 64)).astype(np.float32)
    m = mutual_matches(d1, d2)
    assert len(m) == 200 and np.array_equal(perm[m[:, 1]], m[:, 0])
    twins = np.vstack([d2, d2[:10] + 1e-4])  # ten features now have an almost identical second neighbour
    m = mutual_matches(d1, twins, ratio=0.9)
    assert len(m) <= 190 and not np.isin(perm[:10], m[:, 0]).any()
    assert len(mutual_matches(d1, d2[:0])) == 0


def test_a_planar_warp_of_a_photo_is_verified_as_a_homography(xfeat):
    rgb = _photo("img_00000.jpg")
    h, w = rgb.shape[:2]
    hmat = cv2.getRotationMatrix2D((w / 2, h / 2), 15, 0.9)
    hmat = np.vstack([hmat, [5e-5, 0, 1]])
    warped = cv2.warpPerspective(rgb, hmat, (w, h))
    (k1, d1), (k2, d2) = _xfeat(xfeat, rgb), _xfeat(xfeat, warped)
    v = verify(k1, d1, k2, d2, ratio=None, min_cos=0.82)
    assert v.verified and v.model == "H" and v.inliers > 200


def test_same_place_scores_above_an_unrelated_place(xfeat):
    query = _photo("img_00000.jpg")
    h, w = query.shape[:2]
    crop = cv2.resize(query[h // 6 : h - h // 6, w // 6 : w - w // 6], (w, h))  # a zoomed view of the scene
    other = _photo("img_00050.jpg")
    q = _xfeat(xfeat, query)
    same = verify(*q, *_xfeat(xfeat, crop), ratio=None, min_cos=0.82)
    unrelated = verify(*q, *_xfeat(xfeat, other), ratio=None, min_cos=0.82)
    assert same.inliers > 5 * max(unrelated.inliers, 10)
    # A slightly lower global score is overtaken by the verified view, not by the unrelated one.
    assert fused_score(0.50, same.inliers) > fused_score(0.55, unrelated.inliers)


def test_too_few_or_degenerate_matches_are_unverified_not_errors():
    rng = np.random.default_rng(1)
    few = rng.uniform(0, 600, size=(MIN_MATCHES_TO_FIT - 1, 2))
    assert fit_geometry(few, few + 3).model is None
    same_point = np.tile([[100.0, 200.0]], (40, 1))  # one point repeated: no geometry to fit
    v = fit_geometry(same_point, same_point)
    assert not v.verified and v.inliers == 0 and v.n_matches == 40
    line = np.stack([np.linspace(0, 500, 40), np.linspace(0, 500, 40)], axis=1)  # collinear
    assert fit_geometry(line, line * 1.1).inliers <= 40


def test_fused_score_is_the_global_score_without_inliers_and_saturates():
    assert fused_score(0.4, 0) == pytest.approx(0.4)
    assert fused_score(0.4, 30) > fused_score(0.4, 10) > 0.4
    assert fused_score(0.4, 3000) - fused_score(0.4, 300) < 0.01
