"""The index kinds for large collections (``ivf-rabitq``, ``binary-ivf``) through the real service.

A configuration that names them is fitted by the CLI's own ``fit`` (which trains both quantizers and keeps
them with the pipeline), the worker ingests through them, /locate's use case finds a reference's own photo
first in every search mode, a delete is gone from the next search, and a snapshot writes them (the float
codes inside the ivf-rabitq file) and a reopened service serves from it with the codes memory-mapped."""

from __future__ import annotations

import pytest

from app.engine import configs as configs_mod
from app.engine.configs import PipelineConfig
from app.manifests import read_manifest

#: Small and fast codes (SqueezeNet GeM, 64-d floats and 64 bits) in the two kinds the named ``-ivf``
#: configurations use; the named ones fit EfficientNet-Lite2 and RootSIFT, too slow for a test.
IVF_CONFIG = PipelineConfig(
    name="squeezenet-gem-ivf-test",
    description="SqueezeNet GeM codes, float and binary, in ivf-rabitq and binary-ivf (test)",
    local=None,
    codebook=None,
    cnn_global_weight=1.0,
    cnn_short_side=224,
    pca_dim=64,
    binary="itq",
    bits=64,
    float_index="ivf-rabitq",
    binary_index="binary-ivf",
)


@pytest.fixture
def ivf_models(monkeypatch, models_dir, tmp_path):
    monkeypatch.setitem(configs_mod.CONFIGS, IVF_CONFIG.name, IVF_CONFIG)
    models = tmp_path / "models"
    models.mkdir()
    (models / "squeezenet1_1.onnx").symlink_to(models_dir / "squeezenet1_1.onnx")
    return models


def test_named_configurations_use_the_kinds():
    for name, kinds in [
        ("lite2-hybrid-384-ivf", ("ivf-rabitq", "flat")),
        ("hybrid-bin-ivf", ("ivf-rabitq", "binary-ivf")),
    ]:
        c = configs_mod.CONFIGS[name]
        assert (c.float_index, c.binary_index) == kinds
        base = configs_mod.CONFIGS[name.removesuffix("-ivf")]
        assert c.model_dump(exclude={"name", "description", "float_index", "binary_index"}) == base.model_dump(
            exclude={"name", "description", "float_index", "binary_index"}
        )


def test_fit_ingest_locate_delete_snapshot_reopen(ivf_models, mini_manifest, tmp_path):
    from app.cli import fit
    from app.domain import LocateOptions, Upload
    from app.engine.index.kinds.binary_ivf import BinaryIvfIndex
    from app.engine.index.kinds.ivf_rabitq import IvfCompressedIndex
    from app.engine.pipeline import pipeline_dir
    from app.ingestion.worker import IngestWorker
    from app.usecases.service import GeolocService

    name = IVF_CONFIG.name
    fit(manifest=mini_manifest, config=name, models_dir=ivf_models, seed=0, svm_bank=None, svm_bank_kind="contrastive")
    fitted = pipeline_dir(ivf_models, name)
    assert (fitted / "index-float.faiss").exists() and (fitted / "index-binary.faiss").exists()

    service = GeolocService.open(tmp_path / "data", ivf_models, name)
    db = [r for r in read_manifest(mini_manifest) if r.split == "db"][:16]
    accepted = service.accept([Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in db])
    worker = IngestWorker(service, batch_size=16)
    while worker.run_once():
        pass
    assert service.store.count("indexed") == len(db)
    served = service.collection.index.stats()
    assert (served["float"]["kind"], served["float"]["size"]) == ("ivf-rabitq", len(db))
    assert (served["binary"]["kind"], served["binary"]["size"]) == ("binary-ivf", len(db))

    def own_image_first(svc: GeolocService, i: int) -> None:
        for mode in ("two-stage", "float", "binary"):
            answer = svc.locate(db[i].image.read_bytes(), LocateOptions(top_k=3, mode=mode))
            assert answer.candidates[0].reference_id == accepted.reference_ids[i], mode
            if mode != "binary":  # re-ranked from the exact float codes
                assert answer.candidates[0].score == pytest.approx(1.0, abs=1e-4)

    own_image_first(service, 5)
    gone = accepted.reference_ids[7]
    assert service.delete(gone) is not None
    for mode in ("two-stage", "float", "binary"):
        answer = service.locate(db[7].image.read_bytes(), LocateOptions(top_k=10, mode=mode))
        assert gone not in [c.reference_id for c in answer.candidates], mode
    assert service.collection.write_snapshot()
    table = service.collection.index.float.table  # the serving index reads the codes the snapshot wrote
    assert table.where() == (service.collection.size, 0)
    own_image_first(service, 9)
    service.store.close()

    again = GeolocService.open(tmp_path / "data", ivf_models, name)
    assert again.collection.stats.full_rebuilds == 0  # served from the kinds' own snapshot files
    index = again.collection.index
    assert isinstance(index.float, IvfCompressedIndex) and isinstance(index.binary, BinaryIvfIndex)
    assert index.float.table.where() == (len(db) - 1, 0)
    assert again.collection.size == len(db) - 1 and gone not in index.ids()
    own_image_first(again, 5)
    own_image_first(again, 9)
    again.store.close()
