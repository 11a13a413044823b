"""bench.fusion_replay re-orders a verified run's recorded candidates by other fusion rules: the chosen model's
inliers as ``fit_geometry`` picks them, the first candidate under each rule, and the floor chosen on the
other folds only."""

from __future__ import annotations

from app.engine.matchers.fusion import fused_score
from bench.fusion_replay import by_floor, by_switch, chosen_inliers, heads, lofo_floor, replay


def _query(fold: int, retrieval: list[tuple[int, float, int]], pairs: dict[int, list | None]) -> dict:
    return {
        "fold": fold,
        "verification": {"retrieval": [list(r) for r in retrieval], "pairs": {str(k): v for k, v in pairs.items()}},
    }


def test_the_chosen_models_inliers_follow_fit_geometry() -> None:
    assert chosen_inliers(None) is None
    assert chosen_inliers([40, 0, 0, None]) == 0  # nothing fitted
    assert chosen_inliers([40, 24, 30, None]) == 24  # H explains 80 % of F's inliers: H
    assert chosen_inliers([40, 23, 30, None]) == 30  # else F


def test_a_floor_above_the_confused_candidates_keeps_the_right_first_candidate() -> None:
    # Query 1: the right first candidate has no inliers, a wrong one 30 (a shared facade): a floor of 12 lets
    # the wrong one overtake (0.60 + bonus > 0.62), a floor of 48 does not. Query 2: the right second
    # candidate has 200 inliers and overtakes under either floor.
    run = {
        "queries": [
            _query(0, [(1, 0.62, 1), (2, 0.60, 0)], {1: [5, 0, 0, None], 2: [60, 10, 30, None]}),
            _query(1, [(3, 0.70, 0), (4, 0.65, 1)], {3: [20, 0, 0, None], 4: [300, 200, 210, None]}),
        ]
    }
    hs = heads(run)
    assert hs[0] == (0, [(0.62, True, 0), (0.60, False, 30)])
    assert fused_score(0.60, 30, floor=12) > 0.62 > fused_score(0.60, 30, floor=48)
    low = replay(hs, by_floor(12))
    assert (low["r1"], low["unverified_r1"], low["wins"], low["losses"]) == (0.5, 0.5, 1, 1)
    high = replay(hs, by_floor(48))
    assert (high["r1"], high["wins"], high["losses"]) == (1.0, 1, 0)
    # the switch rule: 30 inliers are not 40; 200 are, and 200 > 2 x 0
    assert replay(hs, by_switch(40, 2.0))["r1"] == 1.0


def test_the_floor_per_fold_comes_from_the_other_folds_only() -> None:
    run = {
        "queries": [
            _query(0, [(1, 0.6, 0)], {1: [50, 0, 10, None]}),  # a wrong candidate with 10 inliers
            _query(1, [(2, 0.6, 0)], {2: [90, 0, 70, None]}),  # one with 70
        ]
    }
    _, floors = lofo_floor(heads(run), 95)
    assert floors == {0: 70.0, 1: 10.0}
