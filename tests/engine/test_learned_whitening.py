"""Learned whitening: pairs from GPS, and a map that ranks a place's other photos above the nuisance."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.errors import ModelNotReady
from app.engine.learned_whitening import LearnedWhitening, Place, gps_pairs
from app.engine.pca import PcaWhitening, l2_normalize

M_PER_DEG_LAT = 111_195.0


def _place(north_m: float, group: str | None = None) -> Place:
    return Place(40.0 + north_m / M_PER_DEG_LAT, -75.0, group)


def test_pairs_follow_gps_and_leave_one_capture_out() -> None:
    places = [_place(0, "a"), _place(0, "a"), _place(10, "b"), _place(0.5, "c"), _place(300, "d"), None]
    pos, neg = gps_pairs(places, pos_radius_m=25, neg_radius_m=100)
    assert {tuple(p) for p in pos} == {(0, 2), (1, 2), (2, 3)}  # (0, 1): one group; (0, 3), (1, 3): < 1 m
    assert {tuple(p) for p in neg} == {(0, 4), (1, 4), (2, 4), (3, 4)}  # the unknown place is in no pair


def _synthetic(seed: int = 0, places: int = 40, per_place: int = 4, dim: int = 300):
    """Photos of a place share its signature (weak) and differ by nuisance along a few strong directions
    (light, viewpoint): PCA-whitening keeps the nuisance, learned whitening should shrink it."""
    rng = np.random.default_rng(seed)
    basis = np.linalg.qr(rng.normal(size=(dim, 50)))[0].T  # 50 orthonormal directions
    signature, nuisance = basis[:10], basis[10:]  # places differ in 10, photos of a place in the other 40
    places_at = rng.normal(size=(places, 10)) @ signature
    x, where = [], []
    for p in range(places):
        for _ in range(per_place):
            x.append(places_at[p] + 1.5 * rng.normal(size=40) @ nuisance + 0.05 * rng.normal(size=dim))
            where.append(_place(p * 200.0 + rng.uniform(0, 10)))
    return l2_normalize(np.asarray(x, np.float32)), where, np.repeat(np.arange(places), per_place)


def _recall_at_1(codes: np.ndarray, label: np.ndarray) -> float:
    sim = codes @ codes.T
    np.fill_diagonal(sim, -np.inf)
    return float(np.mean(label[sim.argmax(axis=1)] == label))


def test_learned_whitening_beats_pca_whitening_on_held_out_places() -> None:
    x, where, label = _synthetic()
    train = label < 25  # fitted on 25 places, tested on the other 15 (never seen in a pair)
    lw = LearnedWhitening.fit(x[train], [w for w, t in zip(where, train, strict=True) if t], dim=64)
    pca = PcaWhitening.fit(x[train], 64, power=0.5)
    test = ~train
    r_lw = _recall_at_1(lw.transform(x[test]), label[test])
    r_pca = _recall_at_1(pca.transform(x[test]), label[test])
    assert r_lw > r_pca + 0.2, (r_lw, r_pca)
    assert lw.dim == 64 and lw.manifest["positive_pairs"] > 0


def test_round_trip_and_refusal(tmp_path) -> None:
    x, where, _ = _synthetic(places=10)
    lw = LearnedWhitening.fit(x, where, dim=16)
    lw.save(tmp_path)
    back = LearnedWhitening.load(tmp_path)
    np.testing.assert_allclose(back.transform(x[:3]), lw.transform(x[:3]), atol=1e-6)
    with pytest.raises(ModelNotReady):
        LearnedWhitening.fit(x, [None] * len(x), dim=16)  # no GPS, no pairs


def test_a_pipeline_fits_saves_and_reloads_its_learned_whitening(tmp_path, monkeypatch) -> None:
    """Through ``Pipeline.fit`` with places (what fit, refit, first start and eval pass), then save/load:
    the reloaded pipeline encodes as the fitted one; without places the fit is refused, not silently PCA."""
    from app.engine import configs as configs_mod
    from app.engine.configs import get_config
    from app.engine.pipeline import Features, Pipeline

    config = get_config("sift-mbvlad").with_overrides({"whitening": "learned", "k": "8", "pca_dim": "16"})
    monkeypatch.setitem(configs_mod.CONFIGS, config.name, config)  # Pipeline.load reads named ones
    rng = np.random.default_rng(0)
    feats, places = [], []
    for p in range(12):
        centre = rng.random((1, 128)).astype(np.float32)
        for _ in range(3):
            local = np.abs(centre + 0.1 * rng.random((60, 128)).astype(np.float32))
            feats.append(Features(local=local / local.sum(1, keepdims=True), xy=rng.random((60, 2)), global_=None))
            places.append(_place(p * 300.0 + rng.uniform(0, 10)))
    pipe = Pipeline(config)
    with pytest.raises(ModelNotReady):
        pipe.fit(feats, seed=0)
    pipe.fit(feats, seed=0, places=places)
    assert isinstance(pipe.pca, LearnedWhitening) and pipe.float_dim == 16
    pipe.save(tmp_path)
    back = Pipeline.load(tmp_path)
    assert isinstance(back.pca, LearnedWhitening)
    np.testing.assert_allclose(back.encode_features(feats[0]).float_, pipe.encode_features(feats[0]).float_, atol=1e-5)
