"""bench.stated_radius: the constant rule's radius recomputed from an evaluation's recorded candidates, judged
on the same confident answers as the radius served."""

from app.engine.estimate import MARGIN_M
from bench.stated_radius import compare

LAT, LON = 39.9515, -75.1920
M = 1 / 111_320  # a metre of latitude, in degrees


def _query(error_m: float, stated_m: float, answer_p: float, confident: bool = True) -> dict:
    """Three candidates at one spot ``error_m`` north of the truth: the constant rule states 0 + 40 m."""
    at = LAT + error_m * M
    return {
        "lat": LAT,
        "lon": LON,
        "candidates": [[at, LON, 0.7], [at, LON, 0.69], [at, LON, 0.68]],
        "estimate": {"lat": at, "lon": LON, "confidence": 0.9, "confident": confident, "answer_p": answer_p,
                     "radius_m": stated_m, "radius_rate": 0.9},
    }  # fmt: skip


def test_both_rules_on_the_same_confident_answers():
    queries = [_query(30, 20, 0.80), _query(50, 60, 0.85), _query(10, 20, 0.95), _query(35, 20, 0.99)]
    out = compare({"queries": [*queries, _query(500, 20, 0.1, confident=False)]})
    # Stated: 30 m outside 20, 50 m within 60, 10 m within 20, 35 m outside 20; the weakest (0.80) misses.
    assert out["stated"] == {"confident": 4, "coverage": 0.5, "coverage_weakest_quartile": 0.0, "median_radius_m": 20.0}
    assert out["constant"]["median_radius_m"] == MARGIN_M  # one spot: 0 m spread + the margin
    assert out["constant"]["coverage"] == 3 / 4 and out["constant"]["coverage_weakest_quartile"] == 1.0
    # A report from before stated radii: the constant rule alone.
    old = [{**q, "estimate": {k: v for k, v in q["estimate"].items() if k != "radius_m"}} for q in queries]
    assert set(compare({"queries": old})) == {"constant"}
