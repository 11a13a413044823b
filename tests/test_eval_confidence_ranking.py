"""`geoloc eval` of a configuration that stores local features, on real penn photos: it verifies
every query from the photos' stored records by default (as /locate does), reports the same queries without
verification, fits each fold's verified rule from stored records, and ranks the answers' confidence against
the training-free baselines (best score, inliers, SUE) consistently with its own per-query records."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sklearn.metrics import average_precision_score

from app.engine.configs import get_config
from app.engine.geo import haversine_m
from app.evaluation.confidence_ranking import SCORES, precision_at_coverage, sue_spread
from app.evaluation.evaluate import evaluate, format_summary, stored_cached
from app.manifests import read_manifest

CONFIG = "lite2-hybrid-384-sv"


def test_precision_at_coverage_counts_ties_by_their_mean():
    label = np.array([1, 0, 1, 0, 0, 1, 0, 0], bool)
    # the top quarter is 2 queries: one clear first (right), then 3 tied (1 of 3 right) for the second place
    score = np.array([5.0, 2.0, 2.0, 2.0, 1.0, 0.0, 0.0, 0.0])
    assert precision_at_coverage(label, score) == pytest.approx((1 + 1 / 3) / 2)
    assert precision_at_coverage(label, -score) == pytest.approx(1 / 3)  # 3 tied for 2 places, 1 of them right


def test_sue_spread_is_zero_on_one_spot_and_follows_the_strong_weights():
    lat, lon = [39.95, 39.95, 39.95], [-75.19, -75.19, -75.19]
    assert sue_spread(lat, lon, [0.9, 0.5, 0.1]) == pytest.approx(0.0, abs=1e-6)
    far = [39.95, 39.951, 39.95]  # the second candidate 111 m north
    # it barely counts when its score is far below the first's (weights exp(-350 d)) ...
    weak = sue_spread(far, lon, [0.9, 0.7, 0.9])
    # ... and spreads the answer when it scores as high as the others
    strong = sue_spread(far, lon, [0.9, 0.9, 0.9])
    assert weak < 1.0 < strong
    assert strong == pytest.approx(111.2**2 * 2 / 9, rel=0.02)  # weighted variance of (0, 111, 0) m


@pytest.fixture(scope="module")
def sv_models_dir(models_dir, lite2, xfeat):
    return models_dir


def test_eval_verifies_from_stored_features_and_ranks_confidence(sv_models_dir, mini_manifest, tmp_path):
    cache = tmp_path / "cache"
    r = evaluate(mini_manifest, get_config(CONFIG), models_dir=sv_models_dir, cache_dir=cache)
    # Verified by default, as /locate answers this configuration; the same queries without verification too.
    assert r.rerank is True and r.without_rerank is not None and "rerank" in r.ms_per_query
    assert set(r.without_rerank.recall_at) == set(r.recall_at)
    assert r.without_rerank.recall_at["20"] == r.recall_at["20"]  # verification re-orders the first 10 only
    rows = read_manifest(mini_manifest)
    assert r.n_query == 9
    verified_pairs = [p for q in r.queries for p in q["verification"]["pairs"].values() if p is not None]
    assert verified_pairs and max(p[1] for p in verified_pairs) > 0  # the stored records did verify pairs
    # The fold's rule for verified answers was fitted on answers verified from stored records.
    cal = r.calibration_per_fold[0]
    assert cal["verified_from"] == "stored features (xfeat-640-n900)" and cal["verified_sampled"] > 0
    assert cal["verified_seconds"] > 0
    # Each photo's record made once, cached on disk; read back the same.
    files = list((cache / "stored-xfeat-640-n900").glob("*.npz"))
    assert len(files) == len(rows)
    pipe_rows = rows[:3]
    from app.engine.pipeline import Pipeline

    again = stored_cached(Pipeline(get_config(CONFIG), models_dir=sv_models_dir), pipe_rows, cache)
    assert len(again) == 3 and all(len(rec) > 0 and len(q) == len(rec) for rec, q in again)

    # The ranking section: the four scores on the verified answers, three without verification.
    ranking = r.confidence_ranking
    assert set(ranking.answers["scores"]) == set(SCORES)
    assert set(ranking.without_verification["scores"]) == {"ours", "best_score", "sue"}
    records = [q["confidence"] for q in r.queries]
    assert ranking.answers["queries"] == len(records) == r.n_query
    label = np.array([x["label"] for x in records], bool)
    assert ranking.answers["right"] == int(label.sum())
    by_image = {row.image.name: row for row in rows}
    for q, x in zip(r.queries, records, strict=True):
        row = by_image[q["image"]]
        lat, lon, _ = q["candidates"][0]
        assert x["label"] == bool(haversine_m(row.lat, row.lon, lat, lon) <= r.radius_m)  # top-1 within 25 m
        assert x["best_score"] == pytest.approx(max(c[2] for c in q["candidates"]), abs=1e-4)
        head = q["candidates"][:10]
        assert -x["sue"] == pytest.approx(sue_spread(*zip(*head, strict=True)), rel=0.05, abs=1.0)
    for name in SCORES:
        got = ranking.answers["scores"][name]
        score = np.array([x[name] for x in records], float)
        if 0 < label.sum() < len(label):
            assert got["auc_pr"] == pytest.approx(average_precision_score(label, score))
        else:
            assert got["auc_pr"] is None
        assert got["precision_at_coverage"] == pytest.approx(precision_at_coverage(label, score))
        assert 0 <= got["precision_at_coverage"] <= 1 and not math.isnan(got["precision_at_coverage"])
    summary = format_summary(r)
    assert "confidence ranking, verified answers" in summary and "  sue: " in summary
    assert "the same queries without verification" in summary
