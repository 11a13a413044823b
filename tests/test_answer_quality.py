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
