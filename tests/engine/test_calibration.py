"""Candidate probabilities: in (0, 1), higher for members of a confident estimate's group than for outliers."""

import numpy as np

from app.engine.calibration import candidate_probabilities
from app.engine.estimate import fuse_position
from app.engine.geo import haversine_m


def _offset(dx_m: float, dy_m: float, lat0=39.952, lon0=-75.193):
    return lat0 + dy_m / 111_320, lon0 + dx_m / (111_320 * np.cos(np.radians(lat0)))


def test_group_members_of_a_confident_estimate_are_likelier():
    pts = [_offset(0, 0), _offset(5, 3), _offset(-4, 2), _offset(300, 300), _offset(-250, 100)]
    lats, lons = np.array(pts).T
    scores = np.array([0.66, 0.65, 0.65, 0.60, 0.59])
    e = fuse_position(lats, lons, scores)
    p = candidate_probabilities(lats, lons, scores, e)
    assert e.confident and ((p > 0) & (p < 1)).all()
    assert p[:3].min() > p[3:].max() and p[0] > 0.5
    # The same candidates scattered: nobody agrees, every probability drops.
    far = [_offset(0, 0), _offset(200, 0), _offset(-200, 50), _offset(300, 300), _offset(-250, 100)]
    flat, flon = np.array(far).T
    e2 = fuse_position(flat, flon, scores)
    p2 = candidate_probabilities(flat, flon, scores, e2)
    assert not e2.confident and p2[0] < p[0] and (p2 < 0.5).all()
    assert haversine_m(e.lat, e.lon, lats[0], lons[0]) < e.radius_m
