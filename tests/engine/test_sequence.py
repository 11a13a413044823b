"""The sequence model on synthetic walks: candidates drawn around a known path, decoys far away."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from app.engine.geo import haversine_m
from app.engine.sequence import (
    ABSENT,
    Motion,
    Observation,
    bursts,
    forward_backward,
    group_places,
    log_transition,
    solve,
    step_places,
    viterbi,
)

LAT0, LON0 = 39.95, -75.19
M_LAT = 1 / 111_320.0  # degrees of latitude per metre


def _walk(n: int, step_m: float = 60.0) -> list[tuple[float, float]]:
    return [(LAT0 + i * step_m * M_LAT, LON0) for i in range(n)]


def _obs(cands: list[tuple[float, float, float]], t: float | None = None) -> Observation:
    a = np.array(cands, float).reshape(-1, 3)
    return Observation(a[:, 0], a[:, 1], a[:, 2], t)


def test_group_places_merges_candidates_within_the_radius():
    lats = np.array([LAT0, LAT0 + 10 * M_LAT, LAT0 + 500 * M_LAT])
    lons = np.full(3, LON0)
    label = group_places(lats, lons, np.array([0.2, 0.5, 0.3]))
    assert label[0] == label[1] != label[2]
    assert label[1] == 0  # the most probable candidate founds the first place


def test_the_walk_picks_the_true_place_over_an_equally_likely_decoy():
    """Each photo alone: the truth and a decoy 2 km away, equally likely (and the decoys jump about). The
    truth is the only place the neighbours agree with."""
    rng = np.random.default_rng(0)
    walk = _walk(8)
    obs = []
    for n, (lat, lon) in enumerate(walk):
        decoy = (LAT0 + rng.uniform(-3000, 3000) * M_LAT, LON0 + rng.uniform(2000, 3000) * M_LAT)
        pair = [(lat, lon, 0.4), (decoy[0], decoy[1], 0.4)]
        obs.append(_obs(pair if n % 2 else pair[::-1], t=60.0 * n))
    result = solve(obs, Motion(speed_mps=2.0))
    for s, members in enumerate(result.steps):
        (photo,) = members
        k = result.path[s]
        assert k != ABSENT
        place = result.places[s]
        assert haversine_m(place.lats[k], place.lons[k], *walk[photo]) < 5
        alone = solve([obs[photo]]).posterior[0]
        assert alone[k] < 0.4  # alone: split between the truth, the decoy and "not here"
        assert result.posterior[s][k] > (0.6 if photo in (0, len(walk) - 1) else 0.7)  # the sequence settles it


def test_photos_from_elsewhere_stay_absent():
    """Low probabilities scattered over a campus: the path never claims a place."""
    rng = np.random.default_rng(1)
    obs = [
        _obs([(LAT0 + rng.uniform(-500, 500) * M_LAT, LON0 + rng.uniform(-500, 500) * M_LAT, 0.05) for _ in range(5)])
        for _ in range(10)
    ]
    result = solve(obs, Motion(step_m=300.0))
    assert (result.path == ABSENT).all()
    assert all(p[-1] > 0.5 for p in result.posterior)


def test_a_confident_photo_keeps_its_place_when_its_neighbours_are_absent():
    walk = _walk(3)
    obs = [
        _obs([(LAT0 + 5000 * M_LAT, LON0, 0.03)]),
        _obs([(*walk[1], 0.95)]),
        _obs([(LAT0 - 5000 * M_LAT, LON0, 0.03)]),
    ]
    result = solve(obs)
    assert list(result.path) == [ABSENT, 0, ABSENT]
    assert result.posterior[1][0] > 0.75


def test_a_jump_beyond_the_speed_bound_is_not_a_path():
    """Two photos 10 s apart cannot be 1 km apart at walking pace: the far candidate loses to the near one
    even though the photo alone prefers it."""
    a = _obs([(LAT0, LON0, 0.9)], t=0.0)
    b = _obs([(LAT0 + 1000 * M_LAT, LON0, 0.5), (LAT0 + 20 * M_LAT + 40 * M_LAT, LON0, 0.4)], t=30.0)
    result = solve([a, b], Motion(speed_mps=2.0), burst_s=0.0)
    k = result.path[1]
    assert k != ABSENT
    assert haversine_m(result.places[1].lats[k], result.places[1].lons[k], LAT0, LON0) < 100
    # With a day between them the far one is reachable, and the photo's own preference wins.
    far = solve([a, _obs(list(zip(b.lats, b.lons, b.p, strict=True)), t=86_400.0)], Motion(speed_mps=2.0))
    k = far.path[1]
    assert haversine_m(far.places[1].lats[k], far.places[1].lons[k], LAT0, LON0) > 900


def test_without_times_the_step_bound_applies():
    near = Motion(step_m=100.0).allowed_m(None)
    assert near == 100.0
    assert Motion(speed_mps=2.0, step_m=100.0).allowed_m(30.0) == 60.0


def test_transitions_favour_compatible_places_and_link_absent_with_a_fixed_weight():
    a = step_places([_obs([(LAT0, LON0, 0.5)])])
    b = step_places([_obs([(LAT0 + 30 * M_LAT, LON0, 0.5), (LAT0 + 3000 * M_LAT, LON0, 0.5)])])
    t = log_transition(a, b, None, Motion(step_m=100.0))
    assert t.shape == (2, 3)
    assert t[0, 0] > 0 and t[0, 1] < -40
    assert t[0, 2] == t[1, 0] < 0 == t[1, 2]  # leaving or entering the collection costs; staying out does not


def test_a_photo_alone_gets_its_own_probability_back():
    """As odds against elsewhere, one place's posterior is its calibrated probability."""
    result = solve([_obs([(LAT0, LON0, 0.7), (LAT0 + 5 * M_LAT, LON0, 0.4)])])
    assert result.posterior[0][0] == pytest.approx(0.7)


def test_a_burst_is_one_step_and_its_photos_evidence_is_fused():
    here = (LAT0, LON0)
    obs = [_obs([(*here, 0.5), (LAT0 + 900 * M_LAT, LON0, 0.3)], t=0.0), _obs([(*here, 0.5)], t=3.0)]
    assert bursts(obs) == [[0, 1]]
    result = solve(obs)
    assert result.steps == [[0, 1]]
    place = result.places[0]
    k = int(np.argmax(result.posterior[0][:-1]))
    assert haversine_m(place.lats[k], place.lons[k], *here) < 1
    alone = solve(obs[:1]).posterior[0]
    assert result.posterior[0][k] > alone.max()  # two photos of one place say more than one
    # Far apart in time, or of different places: separate steps.
    assert bursts([obs[0], _obs([(*here, 0.5)], t=60.0)]) == [[0], [1]]
    assert bursts([obs[0], _obs([(LAT0 + 900 * M_LAT, LON0, 0.6)], t=3.0)]) == [[0], [1]]
    assert bursts([_obs([(*here, 0.5)]), _obs([(*here, 0.5)])]) == [[0], [1]]  # no times: no burst


def _brute(log_e, log_t):
    scores = {}
    for states in itertools.product(*[range(len(e)) for e in log_e]):
        s = sum(log_e[t][k] for t, k in enumerate(states))
        s += sum(log_t[t][states[t], states[t + 1]] for t in range(len(states) - 1))
        scores[states] = s
    return scores


def test_viterbi_and_forward_backward_match_enumeration():
    rng = np.random.default_rng(2)
    sizes = [3, 2, 4, 3]
    log_e = [rng.normal(size=k) for k in sizes]
    log_t = [rng.normal(size=(a, b)) for a, b in zip(sizes, sizes[1:], strict=False)]
    scores = _brute(log_e, log_t)
    assert tuple(viterbi(log_e, log_t)) == max(scores, key=scores.get)
    z = np.logaddexp.reduce(list(scores.values()))
    post = forward_backward(log_e, log_t)
    for t, k in enumerate(sizes):
        for s in range(k):
            want = np.exp(np.logaddexp.reduce([v for st, v in scores.items() if st[t] == s]) - z)
            assert post[t][s] == pytest.approx(want, rel=1e-9)


def test_an_empty_sequence_is_refused_and_a_photo_without_candidates_is_absent():
    with pytest.raises(ValueError):
        solve([])
    result = solve([_obs([]), _obs([(LAT0, LON0, 0.95)])])
    assert result.path[0] == ABSENT
    assert len(result.posterior[0]) == 1


def test_continuity_is_worth_nothing_where_a_step_reaches_across_the_collection():
    """The gain of two places in reach: full without a known extent or where the reach is small against the
    collection, 1 where the reach spans it; a walk of weak photos is placed only where continuity says something."""
    from app.engine.sequence import CONTINUITY_GAIN

    assert Motion(step_m=500).continuity_gain(None) == CONTINUITY_GAIN
    assert Motion(step_m=500, extent_m=300).continuity_gain(None) == 1.0
    assert 1.0 < Motion(step_m=50, extent_m=3000).continuity_gain(None) < CONTINUITY_GAIN
    assert Motion(speed_mps=2, extent_m=3000).continuity_gain(10.0) > Motion(
        speed_mps=2, extent_m=3000
    ).continuity_gain(60.0)
    walk = _walk(8)  # each photo: its true place at 0.4, nothing else
    obs = [_obs([(lat, lon, 0.4)]) for lat, lon in walk]
    placed = solve(obs, Motion(step_m=100, extent_m=6000))
    assert (placed.path != ABSENT).all()
    spanned = solve(obs, Motion(step_m=100, extent_m=300))  # every place within reach of every other
    assert (spanned.path == ABSENT).all()
