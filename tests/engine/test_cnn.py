"""CNN helpers: GeM pooling, bilinear sampling at keypoints, the resize before the net."""

import numpy as np
import pytest

from app.engine.dense import gem_pool, resize_short_side, sample_at
from app.engine.imageio import load_image


def test_gem_is_unit_length_and_between_mean_and_max():
    rng = np.random.default_rng(0)
    x = rng.random((5, 6, 8)).astype(np.float32)
    g = gem_pool(x, p=3)
    assert np.linalg.norm(g) == pytest.approx(1.0, abs=1e-5)
    raw = np.power(np.mean(x.reshape(-1, 8) ** 3, 0), 1 / 3)
    flat = x.reshape(-1, 8)
    assert (raw >= flat.mean(0) - 1e-6).all() and (raw <= flat.max(0) + 1e-6).all()


def test_sampling_at_cell_centres_returns_the_cells():
    fmap = np.arange(4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3)
    xy = np.array([[(c + 0.5) / 5, (r + 0.5) / 4] for r in range(4) for c in range(5)], np.float32)
    out = sample_at(fmap, xy)
    assert np.allclose(out, fmap.reshape(-1, 3))
    mid = sample_at(fmap, np.array([[1.0 / 5, 0.5 / 4]], np.float32))  # halfway between cells 0 and 1
    assert np.allclose(mid[0], (fmap[0, 0] + fmap[0, 1]) / 2)


def test_resize_keeps_aspect():
    out = resize_short_side(np.zeros((300, 400, 3), np.uint8), 224)
    assert out.shape[:2] == (224, 299)


def test_a_crop_is_closer_to_its_photo_than_other_places_are(squeezenet, penn_index):
    """GeM of a photo is more similar to a crop of itself than to crops of photos 100+ m away."""
    from app.engine.geo import haversine_m
    from tests.conftest import PENN

    rows = [r for r in penn_index if r["photo"]]
    a = rows[0]

    def g(path):
        return gem_pool(squeezenet.features(load_image((PENN / path).read_bytes()).rgb, 224).fire9)

    ga = g(a["photo"])
    own = g(a["crops"].split(";")[0])
    far = [r for r in rows if haversine_m(float(a["lat"]), float(a["lon"]), float(r["lat"]), float(r["lon"])) > 100]
    others = [g(r["crops"].split(";")[0]) for r in far[:5]]
    assert all(ga @ own > ga @ o for o in others)


def test_gem_matches_the_float64_formula_for_every_p():
    """The p = 3 fast path (float32 cubes summed in float64) and the general path agree with the textbook
    formula in float64."""
    rng = np.random.default_rng(1)
    x = rng.random((7, 9, 40)).astype(np.float32)
    for p in (3.0, 2.0, 4.5):
        flat = x.reshape(-1, 40).astype(np.float64)
        want = np.power(np.mean(np.power(flat, p), 0), 1 / p)
        assert np.allclose(gem_pool(x, p), want / np.linalg.norm(want), atol=1e-6)


def test_joined_descriptors_are_the_unit_parts_side_by_side():
    from app.engine.dense import join_sampled

    rng = np.random.default_rng(2)
    fmap = rng.random((4, 5, 6)).astype(np.float32)
    local = rng.random((9, 3)).astype(np.float32)
    local[0] = 0  # a zero descriptor stays zero, it is not divided by its norm
    xy = rng.random((9, 2)).astype(np.float32)
    out = join_sampled(local, fmap, xy, 0.5)
    sampled = sample_at(fmap, xy)
    unit = lambda a: a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-30)  # noqa: E731
    assert out.shape == (9, 9) and out.dtype == np.float32
    assert np.allclose(out[:, :3], unit(local)) and not out[0, :3].any()
    assert np.allclose(out[:, 3:], 0.5 * unit(sampled), atol=1e-6)
