"""An index kind is a plug-in: one module (here, this test) that registers itself, one named configuration.

The toy kind is a real FAISS index the service does not ship: an 8-bit scalar quantizer, which needs
training. The CLI's own ``fit`` must train it (the explicit step, saved with the fitted pipeline), the
worker adds every reference through it, /locate's use case searches it, a snapshot writes and reloads it,
the collection reports it as the serving kind, and a refit trains the new generation's: all found through
the registry alone."""

from __future__ import annotations

import faiss
import numpy as np
import pytest

from app.engine import configs as configs_mod
from app.engine.configs import PipelineConfig
from app.engine.index.base import register_index_kind
from app.engine.index.faiss_index import FaissIndex
from app.manifests import read_manifest

TOY_KIND = "toy-sq8"


class ToyScalarQuantizedIndex(FaissIndex):
    """What a new kind's module holds: the FAISS index it wraps, its parameters, and its registration."""

    kind = TOY_KIND

    def _make(self):
        if self.binary:
            raise ValueError("the toy scalar quantizer indexes float codes only")
        inner = faiss.IndexScalarQuantizer(self.dim, faiss.ScalarQuantizer.QT_8bit, faiss.METRIC_INNER_PRODUCT)
        return faiss.IndexIDMap2(inner)

    def params(self) -> dict:
        return {"code_bytes": self.dim}


register_index_kind(TOY_KIND, ToyScalarQuantizedIndex)

TOY_CONFIG = PipelineConfig(
    name="toy-sq8-gem",
    description="SqueezeNet GeM codes in a toy 8-bit scalar-quantized index (test plug-in)",
    local=None,
    codebook=None,
    cnn_global_weight=1.0,
    cnn_short_side=224,
    pca_dim=64,
    float_index=TOY_KIND,
)


@pytest.fixture
def toy_config(monkeypatch, models_dir):
    """The configuration, for this test only (the registry of configurations is a plain dict)."""
    monkeypatch.setitem(configs_mod.CONFIGS, TOY_CONFIG.name, TOY_CONFIG)
    return models_dir


def test_a_toy_index_kind_fits_ingests_and_locates(toy_config, mini_manifest, tmp_path):
    from app.cli import fit
    from app.domain import LocateOptions, Upload
    from app.engine.pipeline import pipeline_dir
    from app.ingestion.worker import IngestWorker
    from app.jobs.refit import RefitOptions, refit
    from app.usecases.service import GeolocService

    models = tmp_path / "models"
    models.mkdir()
    (models / "squeezenet1_1.onnx").symlink_to(toy_config / "squeezenet1_1.onnx")
    name = TOY_CONFIG.name
    fit(manifest=mini_manifest, config=name, models_dir=models, seed=0, svm_bank=None, svm_bank_kind="contrastive")
    assert (pipeline_dir(models, TOY_CONFIG.name) / "index-float.faiss").exists()  # the trained quantizer

    service = GeolocService.open(tmp_path / "data", models, TOY_CONFIG.name)
    assert service.pipeline.trained_index is not None
    db = [r for r in read_manifest(mini_manifest) if r.split == "db"][:12]
    accepted = service.accept([Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in db])
    worker = IngestWorker(service, batch_size=16)
    while worker.run_once():
        pass
    assert service.store.count("indexed") == len(db)
    served = service.collection.index.stats()["float"]
    assert (served["kind"], served["size"]) == (TOY_KIND, len(db))
    assert served["code_bytes"] == service.pipeline.float_dim

    def own_image_first(svc: GeolocService) -> None:
        answer = svc.locate(db[5].image.read_bytes(), LocateOptions(top_k=3))
        assert answer.config == TOY_CONFIG.name
        assert answer.candidates[0].reference_id == accepted.reference_ids[5]
        assert answer.candidates[0].score == pytest.approx(1.0, abs=1e-2)  # 8-bit codes: close, not exact

    own_image_first(service)
    assert service.collection.write_snapshot()
    service.store.close()

    again = GeolocService.open(tmp_path / "data", models, TOY_CONFIG.name)
    assert again.collection.stats.full_rebuilds == 0  # loaded from the toy kind's own snapshot files
    assert isinstance(again.collection.index.float, ToyScalarQuantizedIndex)
    assert again.collection.size == len(db)
    own_image_first(again)
    again.store.close()

    # A refit trains the new generation's quantizer on its own codes and keeps it with that pipeline.
    summary = refit(tmp_path / "data", models, RefitOptions(sample=12, svm_bank="none", seed=3), progress=False)
    assert summary.generation == 1 and summary.reencoded == len(db)
    assert (tmp_path / "data" / summary.pipeline / "index-float.faiss").exists()
    refitted = GeolocService.open(tmp_path / "data", models, TOY_CONFIG.name)
    assert refitted.collection.generation == 1 and refitted.pipeline.trained_index is not None
    own_image_first(refitted)
    refitted.store.close()


def test_the_toy_kind_refuses_codes_before_training():
    from app.engine.index.base import IndexNotTrained, build_index

    idx = build_index(TOY_KIND, 8, False)
    with pytest.raises(IndexNotTrained):
        idx.add(np.arange(2), np.eye(2, 8, dtype=np.float32))
