"""A matcher is a plug-in: one module (``tests/engine/toy_matcher.py``) that registers itself and its named
configuration, and nothing else edited. The configuration fits (the CLI's own ``fit``), its references are
ingested by the worker, and /locate's use case verifies with the toy: its numbers are the toy's."""

from __future__ import annotations

import importlib
import sys

import pytest

from app.engine import configs as configs_mod
from app.engine import registry
from app.engine.registry import Kind, UnknownModel
from app.manifests import read_manifest

MODULE = "tests.engine.toy_matcher"


@pytest.fixture
def toy():
    """Import the plug-in's module (its registration runs), and forget it after the test."""
    module = importlib.import_module(MODULE)
    yield module
    registry.PLUGINS[Kind.MATCHER].pop(module.NAME, None)
    configs_mod.CONFIGS.pop(module.CONFIG.name, None)
    sys.modules.pop(MODULE, None)


def test_without_its_module_the_matcher_is_unknown():
    with pytest.raises(UnknownModel, match="unknown matcher 'toy-orb'"):
        registry.create(Kind.MATCHER, "toy-orb")


def test_a_toy_matcher_fits_ingests_and_locates_with_verification(toy, mini_manifest, tmp_path):
    from app.cli import fit
    from app.domain import LocateOptions, Upload
    from app.engine.imageio import load_image
    from app.ingestion.worker import IngestWorker
    from app.usecases.service import GeolocService

    models = tmp_path / "models"
    models.mkdir()
    name = toy.CONFIG.name
    fit(manifest=mini_manifest, config=name, models_dir=models, seed=0, svm_bank=None, svm_bank_kind="contrastive")
    service = GeolocService.open(tmp_path / "data", models, name)
    assert isinstance(service.pipeline.matcher, toy.ToyOrbMatcher)

    db = [r for r in read_manifest(mini_manifest) if r.split == "db"][:12]
    accepted = service.accept([Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in db])
    worker = IngestWorker(service, batch_size=16)
    while worker.run_once():
        pass
    assert service.store.count("indexed") == len(db)

    query = db[4].image.read_bytes()
    answer = service.locate(query, LocateOptions(top_k=5, rerank=True))
    assert answer.config == name and "rerank" in answer.timings_ms
    own = accepted.reference_ids[4]
    assert answer.candidates[0].reference_id == own
    # Every verified candidate's outcome is the toy's own, for that pair of stored images.
    matcher = toy.ToyOrbMatcher()
    q = matcher.features(load_image(query).rgb)
    ids = dict(zip(accepted.reference_ids, db, strict=True))
    assert answer.verification
    for ref_id, v in answer.verification.items():
        assert v is not None
        expected = matcher.match(q, matcher.features(load_image(ids[ref_id].image.read_bytes()).rgb))
        assert (v.n_matches, v.inliers, v.model) == (expected.n_matches, expected.inliers, expected.model)
    assert answer.verification[own].verified and answer.verification[own].inliers >= 100
    assert answer.candidates[0].inliers == answer.verification[own].inliers
