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
