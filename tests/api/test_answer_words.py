"""The words `geoloc locate` puts on an answer: a photo with no confident estimate is never told to
"trust the ranked candidates", and --min-score that hides every candidate says so instead of "no reference
could be compared (None)". Real `geoloc locate` on the mini collection and penn photos."""

from __future__ import annotations

import json

from tests.api.conftest import CONFIG
from tests.conftest import PENN
from tests.test_cli import geoloc


def _locate(data, models, photo, *extra) -> str:
    args = ["locate", str(photo), "--data-dir", str(data), "--models-dir", str(models), "--config", CONFIG]
    return geoloc(*args, *extra).stdout


def test_an_answer_without_an_estimate_asks_for_a_comparison_not_trust(mini_collection, fitted_models):
    photo = PENN / "photos" / "img_00006.jpg"  # a query row of the mini manifest, with EXIF GPS
    out = json.loads(_locate(mini_collection, fitted_models, photo, "--compare-exif"))
    assert out["estimate"] is None, "the precondition: no confident estimate"
    sentence = out["exif_check"]["sentence"]
    assert "trust" not in sentence and "compare" in sentence, sentence


def test_a_min_score_that_hides_every_candidate_says_so(mini_collection, fitted_models):
    photo = PENN / "photos" / "img_00006.jpg"
    out = json.loads(_locate(mini_collection, fitted_models, photo, "--min-score", "0.999"))
    assert out["candidates"] == []
    words = _locate(mini_collection, fitted_models, photo, "--min-score", "0.999", "--brief")
    assert "no reference could be compared" not in words and "(None)" not in words, words
    assert "--min-score" in words
