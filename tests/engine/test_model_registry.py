"""A global model is a plug-in: one module (here, this test) that registers it, one named configuration.

The toy model is a real ONNX graph the test writes (one strided convolution and a ReLU); fit (the CLI's
own ``fit``), ingestion through the worker and /locate's use case find it through the registry alone, and
the Ray packaging ships its file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from app.engine import configs as configs_mod
from app.engine import registry
from app.engine.configs import PipelineConfig, get_config
from app.engine.dense import resize_short_side
from app.engine.models.base import OnnxModel
from app.engine.registry import Kind, Plugin, UnknownModel, files_for
from app.manifests import read_manifest

TOY_FILE = "toy.onnx"
TOY_DIM = 8


class ToyModel(OnnxModel):
    """What a new global model's module holds: its file, its map's channels, and ``dense``."""

    filename = TOY_FILE
    dim = TOY_DIM

    def dense(self, rgb: np.ndarray, short_side: int) -> np.ndarray:
        x = np.ascontiguousarray(resize_short_side(rgb, short_side).astype(np.float32).transpose(2, 0, 1)[None])
        (out,) = self.predict({"image_rgb": x}, ["dense"])
        return out[0].transpose(1, 2, 0)


def write_toy_onnx(path: Path) -> None:
    rng = np.random.default_rng(0)
    weights = numpy_helper.from_array(rng.normal(0, 0.05, (TOY_DIM, 3, 8, 8)).astype(np.float32), "w")
    graph = helper.make_graph(
        [
            helper.make_node("Conv", ["image_rgb", "w"], ["conv"], strides=[8, 8], kernel_shape=[8, 8]),
            helper.make_node("Relu", ["conv"], ["dense"]),
        ],
        "toy",
        [helper.make_tensor_value_info("image_rgb", TensorProto.FLOAT, [1, 3, None, None])],
        [helper.make_tensor_value_info("dense", TensorProto.FLOAT, [1, TOY_DIM, None, None])],
        initializer=[weights],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save(model, path)


TOY_CONFIG = PipelineConfig(
    name="toy-gem",
    description="a toy global model's GeM vector (test plug-in)",
    local=None,
    codebook=None,
    global_model="toy",
    cnn_global_weight=1.0,
    cnn_short_side=96,
    pca_dim=None,
)


@pytest.fixture
def toy_registered(monkeypatch, tmp_path):
    """Register the plug-in for this test only (what its module's ``register`` call does, undone after)."""
    models = tmp_path / "models"
    models.mkdir()
    write_toy_onnx(models / TOY_FILE)
    toy = Plugin(Kind.GLOBAL_MODEL, "toy", lambda d: ToyModel(d / TOY_FILE), (TOY_FILE,), dim=TOY_DIM)
    monkeypatch.setitem(registry.PLUGINS[Kind.GLOBAL_MODEL], "toy", toy)
    monkeypatch.setitem(configs_mod.CONFIGS, TOY_CONFIG.name, TOY_CONFIG)
    return models


def test_a_toy_global_model_fits_ingests_and_locates(toy_registered, mini_manifest, tmp_path):
    from app.cli import fit
    from app.domain import LocateOptions, Upload
    from app.ingestion.encoding.ray import model_files
    from app.ingestion.worker import IngestWorker
    from app.usecases.service import GeolocService

    models = toy_registered
    fit(manifest=mini_manifest, config="toy-gem", models_dir=models, seed=0, svm_bank=None, svm_bank_kind="contrastive")
    service = GeolocService.open(tmp_path / "data", models, "toy-gem")
    assert service.pipeline.float_dim == TOY_DIM
    assert isinstance(service.pipeline.global_model, ToyModel)

    db = [r for r in read_manifest(mini_manifest) if r.split == "db"][:12]
    accepted = service.accept([Upload(r.image.read_bytes(), r.image.name, r.lat, r.lon) for r in db])
    worker = IngestWorker(service, batch_size=16)
    while worker.run_once():
        pass
    assert service.store.count("indexed") == len(db)

    # A reference's own image comes back first: the toy model's codes are what the index holds.
    answer = service.locate(db[5].image.read_bytes(), LocateOptions(top_k=3))
    assert answer.config == "toy-gem"
    assert answer.candidates[0].reference_id == accepted.reference_ids[5]
    assert answer.candidates[0].score == pytest.approx(1.0, abs=1e-4)

    # Ray ships what the registry says the configuration reads.
    from app.engine.pipeline import PipelineSource

    shipped = model_files(PipelineSource.default(models, "toy-gem"))
    assert TOY_FILE in shipped and "squeezenet1_1.onnx" not in shipped


def test_files_for_names_each_configurations_models():
    assert files_for(get_config("hybrid")) == ["squeezenet1_1.onnx"]
    assert files_for(get_config("hybrid-xfeat")) == ["squeezenet1_1.onnx", "xfeat.onnx"]
    assert files_for(get_config("sift-mbvlad")) == []
    assert files_for(get_config("xfeat-mbvlad")) == ["xfeat.onnx"]


def test_an_unknown_model_is_named(tmp_path):
    from app.engine.pipeline import Pipeline

    with pytest.raises(UnknownModel, match="unknown global model 'nope'"):
        Pipeline(TOY_CONFIG.model_copy(update={"global_model": "nope"}), models_dir=tmp_path)
    with pytest.raises(UnknownModel, match="unknown matcher"):
        registry.create(Kind.MATCHER, "nope")


def test_the_default_matcher_is_a_registry_entry():
    from app.engine.matchers.sift_mnn import SiftMnnMatcher
    from app.engine.pipeline import Pipeline

    pipe = Pipeline(get_config("sift-mbvlad"))
    assert get_config("hybrid").matcher == "sift-mnn"
    assert isinstance(pipe.matcher, SiftMnnMatcher)
