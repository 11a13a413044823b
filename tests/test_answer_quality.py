"""The evaluation's answer-quality figures from answer records (``app.evaluation.evaluate.answer_quality``)."""

from app.evaluation.evaluate import answer_quality


def _record(confident: bool, error_m: float, p=(0.5,), within=(True,)) -> dict:
    return {
        "confident": confident,
        "right": error_m <= 25,
        "right_2x": error_m <= 50,
        "code": "confident" if confident else "ambiguous",
        "p": list(p),
        "within": list(within),
    }


def test_confident_precision_is_counted_at_the_radius_and_at_twice_it():
    present = [_record(True, 10), _record(True, 30), _record(True, 80), _record(False, 5)]
    q = answer_quality(present, [], None)
    assert q["coverage"] == 0.75
    assert q["precision"] == 1 / 3  # only the 10 m estimate is within 25 m
    assert q["precision_at_2x_radius"] == 2 / 3  # the 30 m one is a near miss, the 80 m one is not
    assert q["brier"] == 0.25 and q["reason_codes"] == {"confident": 3, "ambiguous": 1}


def test_no_confident_answer_has_no_precision():
    q = answer_quality([_record(False, 5)], [_record(False, 500, p=(0.02,), within=(False,))], 100)
    assert q["precision"] is None and q["precision_at_2x_radius"] is None
    assert q["absent_confident"] == 0 and q["absent_mean_best_p"] == 0.02


def test_the_stated_radius_is_judged_overall_and_in_the_weakest_quartile():
    """Of the confident answers: the truth within the radius each stated, overall and in the quarter with
    the weakest evidence; the median radius; the rate stated. Answers that are not confident do not count."""
    present = [
        {**_record(True, err), "error_m": err, "radius_m": radius, "radius_rate": 0.9, "strength": s}
        for err, radius, s in [(50, 40, 0.80), (10, 40, 0.81), (5, 20, 0.95), (8, 20, 0.97),
                               (30, 20, 0.96), (1, 20, 0.99), (2, 20, 0.98), (3, 20, 0.99)]
    ] + [{**_record(False, 500), "error_m": 500, "radius_m": 60, "radius_rate": None, "strength": 0.1}]  # fmt: skip
    q = answer_quality(present, [], None)
    assert q["radius_coverage"] == 6 / 8  # 50 m > 40 m and 30 m > 20 m miss
    assert q["radius_coverage_weakest_quartile"] == 1 / 2  # the two weakest: 50 m in 40 (miss), 10 m in 40
    assert q["median_radius_m"] == 20 and q["radius_rate"] == 0.9
    # The constant rule's answers state no rate.
    plain = [{**r, "radius_rate": None} for r in present]
    assert answer_quality(plain, [], None)["radius_rate"] is None
