"""Search modes and the fused position estimate."""

import numpy as np
import pytest

from app.engine.configs import CONFIGS, configs_serving, get_config
from app.engine.estimate import MARGIN_M, RADIUS_FLOOR_M, fuse_position
from app.engine.geo import haversine_m
from app.engine.index.references import ReferenceIndex, UnsupportedMode


def _codes(n=500, dim=64, bits=64, seed=0):
    rng = np.random.default_rng(seed)
    f = rng.standard_normal((n, dim)).astype(np.float32)
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    b = np.packbits(f[:, :bits] > 0, axis=1)
    return f, b


def test_two_stage_reranks_the_shortlist_exactly():
    f, b = _codes()
    idx = ReferenceIndex(get_config("hybrid-bin"), 64, 64)
    idx.add(np.arange(500), f, b)
    q = f[10] + 0.05 * np.random.default_rng(1).standard_normal(64).astype(np.float32)
    q /= np.linalg.norm(q)
    qb = np.packbits(q[:64] > 0)
    s_two, i_two = idx.search(q, qb, 5, "two-stage")
    s_float, i_float = idx.search(q, qb, 5, "float")
    assert i_two[0] == 10 and i_float[0] == 10
    assert np.allclose(s_two[0], s_float[0])
    _, i_bin = idx.search(q, qb, 5, "binary")
    assert i_bin[0] == 10


def test_modes_follow_the_configuration():
    assert get_config("hybrid").modes == ["float"]
    assert get_config("orb-mbvlad-bin").modes == ["binary"]
    assert get_config("hybrid-bin").modes[0] == "two-stage"
    idx = ReferenceIndex(get_config("orb-mbvlad-bin"), None, 64, serving=configs_serving)
    assert idx.check_mode(None) == "binary"
    with pytest.raises(UnsupportedMode, match="serves binary; the named configurations that serve float are "):
        idx.check_mode("float")
    with pytest.raises(UnsupportedMode, match="serves binary; the named configurations that serve float are "):
        idx.copy().check_mode("float")  # a copy (``Pipeline.new_index``'s) keeps what it was told


def test_every_named_configuration_exists():
    assert {"sift-vlad-kmeans", "sift-mbvlad", "orb-mbvlad-bin", "squeezenet-gem", "hybrid", "hybrid-bin"} <= set(
        CONFIGS
    )


BASE = (39.9520, -75.1930)


def _offset(north_m: float, east_m: float):
    return BASE[0] + north_m / 111_320, BASE[1] + east_m / (111_320 * np.cos(np.radians(BASE[0])))


def test_agreeing_candidates_give_a_confident_estimate_at_their_centre():
    pts = [_offset(0, 0), _offset(5, 3), _offset(-4, 2), _offset(300, 300), _offset(-250, 100)]
    lats, lons = np.array(pts).T
    scores = np.array([0.90, 0.89, 0.88, 0.80, 0.79])
    e = fuse_position(lats, lons, scores)
    assert e.confident and e.support == 3
    assert haversine_m(e.lat, e.lon, *_offset(0.5, 1.7)) < 5
    farthest = max(haversine_m(e.lat, e.lon, la, lo) for la, lo in pts[:3])
    assert 0.5 < e.confidence <= 1 and e.radius_m == pytest.approx(max(farthest + MARGIN_M, RADIUS_FLOOR_M))
    assert e.radius_m >= farthest and e.members == (True, True, True, False, False)


def test_disagreeing_candidates_are_not_confident():
    pts = [_offset(0, 0), _offset(200, 0), _offset(0, 200), _offset(-200, 0), _offset(0, -200)]
    lats, lons = np.array(pts).T
    e = fuse_position(lats, lons, np.array([0.80, 0.80, 0.79, 0.79, 0.80]))
    assert not e.confident and "ambiguous" in e.reason
    assert e.confidence < 0.3


def test_no_candidates_gives_a_reason():
    e = fuse_position(np.zeros(0), np.zeros(0), np.zeros(0))
    assert e.lat is None and not e.confident and "no candidates" in e.reason
