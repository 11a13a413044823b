"""Verification as pure functions: matching, the minimum before OpenCV, the H-or-F rule, the fused score."""

import cv2
import numpy as np
import pytest

from app.engine.geo import haversine_m
from app.engine.imageio import ImageLimits, load_image
from app.engine.matchers.fusion import FUSION_FLOOR, fused_score
from app.engine.matchers.geometry import MIN_MATCHES_TO_FIT, fit_geometry, mutual_matches, verify
from app.engine.matchers.sift_mnn import SiftMnnMatcher
from app.usecases.locate import order_by_verification, verify_candidates
from tests.conftest import PENN, penn_photo


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


def test_fused_score_is_the_global_score_up_to_the_floor_then_rises_and_saturates():
    assert fused_score(0.4, 0) == pytest.approx(0.4)
    assert fused_score(0.4, FUSION_FLOOR) == pytest.approx(0.4)  # chance inliers are worth nothing
    assert fused_score(0.4, FUSION_FLOOR + 30) > fused_score(0.4, FUSION_FLOOR + 10) > 0.4
    assert fused_score(0.4, 3000) - fused_score(0.4, 300) < 0.01


# -- the H-or-F rule and the minimum of matches, on synthetic correspondences ----------------------------
_K = np.array([[500.0, 0, 400], [0, 500, 300], [0, 0, 1]])


def _project(points: np.ndarray, rot: np.ndarray, t: np.ndarray) -> np.ndarray:
    cam = points @ rot.T + t
    px = cam @ _K.T
    return px[:, :2] / px[:, 2:]


def _two_views(points: np.ndarray, n_outliers: int = 40, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions of ``points`` in two cameras 1 unit apart (turned 5 degrees), 0.3 px noise, plus
    ``n_outliers`` random pairs: the matches a real matcher would hand over."""
    rng = np.random.default_rng(seed)
    rot, _ = cv2.Rodrigues(np.array([0.0, np.radians(5), 0.0]))
    p1 = _project(points, np.eye(3), np.zeros(3)) + rng.normal(0, 0.3, (len(points), 2))
    p2 = _project(points, rot, np.array([-1.0, 0.0, 0.1])) + rng.normal(0, 0.3, (len(points), 2))
    out1, out2 = rng.uniform([0, 0], [800, 600], (n_outliers, 2)), rng.uniform([0, 0], [800, 600], (n_outliers, 2))
    return np.vstack([p1, out1]), np.vstack([p2, out2])


def _scene(n: int, plane: bool, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-3, 3, n), rng.uniform(-2, 2, n)
    z = 8 + 0.4 * x if plane else rng.uniform(4, 14, n)  # a tilted facade, or depth spread over 4-14 units
    return np.stack([x * z / 8, y * z / 8, z], axis=1)


def test_a_plane_is_fitted_as_a_homography():
    p1, p2 = _two_views(_scene(200, plane=True))
    v = fit_geometry(p1, p2)
    assert v.model == "H" and v.h_inliers >= 190 and v.f_inliers >= v.h_inliers  # F has at least H's inliers
    assert v.inliers == v.h_inliers


def test_a_scene_with_parallax_is_fitted_as_a_fundamental_matrix():
    p1, p2 = _two_views(_scene(200, plane=False))
    v = fit_geometry(p1, p2)
    assert v.model == "F" and v.inliers == v.f_inliers >= 190
    assert v.h_inliers < 0.8 * v.f_inliers  # no homography explains a scene with depth
    # With h_share 0 the rule always keeps H: the setting is what makes F win here.
    assert fit_geometry(p1, p2, h_share=0.0).model == "H"


def test_no_model_is_fitted_below_the_minimum_of_matches():
    p1, p2 = _two_views(_scene(MIN_MATCHES_TO_FIT, plane=True), n_outliers=0)
    assert fit_geometry(p1, p2).model == "H"  # exactly the minimum: fitted
    short = fit_geometry(p1[:-1], p2[:-1])  # one fewer: OpenCV is not called, whatever the geometry
    assert short.model is None and short.inliers == 0 and short.n_matches == MIN_MATCHES_TO_FIT - 1


# -- a landmark-style check through the core's verification ---------------------------------------------
class _Images:
    """Encoded images as the core's ``ReferenceSource`` for verification (ids index the list)."""

    def __init__(self, images: list[bytes]):
        self.images = images

    def image_bytes(self, ref_id: int) -> bytes | None:
        return self.images[ref_id] if ref_id < len(self.images) else None


def _jpeg(rgb: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].tobytes()


def test_a_photos_crops_and_rotations_are_put_first_and_unrelated_photos_keep_their_order(penn_index):
    """Retrieval ranked the six photos farthest from the query (about 200 m away) above three views of the
    query's scene: a crop from the data set, a 25 degree rotation zoomed out, a quarter turn. Verification
    must lift the three views to the top and leave the unrelated ones, with at most chance inliers, in
    their order."""
    by_id = {r["photo_id"]: r for r in penn_index}
    q = by_id["img_00000"]

    def away(r: dict) -> float:
        return float(haversine_m(float(q["lat"]), float(q["lon"]), float(r["lat"]), float(r["lon"])))

    far = sorted((r for r in penn_index if r["photo"]), key=away)[-6:][::-1]  # the farthest six photos
    query = load_image(penn_photo("img_00000.jpg").read_bytes()).rgb
    h, w = query.shape[:2]
    views = [
        (PENN / q["crops"].split(";")[0]).read_bytes(),
        _jpeg(cv2.warpAffine(query, cv2.getRotationMatrix2D((w / 2, h / 2), 25, 0.8), (w, h))),
        _jpeg(np.ascontiguousarray(np.rot90(query))),
    ]
    images = [(PENN / r["photo"]).read_bytes() for r in far] + views
    ranked = [(i, 0.6 - 0.01 * i) for i in range(len(images))]  # the unrelated photos first
    inliers = verify_candidates(query, [i for i, _ in ranked], _Images(images), ImageLimits(), SiftMnnMatcher())
    out = [i for i, _ in order_by_verification(ranked, inliers)]
    assert set(out[:3]) == {6, 7, 8}, inliers
    assert all(inliers[i] > 100 for i in (6, 7, 8)), inliers
    assert all(inliers[i] <= FUSION_FLOOR for i in range(6)), inliers  # chance inliers only
    assert out[3:] == list(range(6))
