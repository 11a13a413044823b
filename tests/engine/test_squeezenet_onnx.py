"""The converted SqueezeNet must classify the check images as NOTES.md says the original does."""

import json

import cv2
import numpy as np
import onnx
import pytest

from app.engine.convert.squeezenet_onnx import build_squeezenet_onnx
from app.engine.errors import ModelBuildError
from app.engine.models.squeezenet import MODEL_FILENAME, softmax
from tests.conftest import CHECK_IMAGES


def _top(squeezenet, name: str, size: int, n: int = 3) -> list[int]:
    rgb = cv2.cvtColor(cv2.imread(str(CHECK_IMAGES / name)), cv2.COLOR_BGR2RGB)
    out = squeezenet.run(cv2.resize(rgb, (size, size), interpolation=cv2.INTER_LINEAR))
    p = softmax(out.logits)
    assert abs(p.sum() - 1) < 1e-4
    return [int(i) for i in np.argsort(-p)[:n]]


@pytest.mark.parametrize("size", [224, 227])
def test_check_images_get_the_documented_classes(squeezenet, size):
    assert _top(squeezenet, "car.png", size)[0] == 817  # sports car
    fox = _top(squeezenet, "fox.jpg", size)
    assert fox[:2] == [280, 278]  # grey fox, kit fox
    assert {281, 282} <= set(_top(squeezenet, "cat.jpg", size))  # tabby, tiger cat in the top 3
    assert _top(squeezenet, "horse-cart.jpg", size)[0] in (603, 339)  # horse cart or sorrel


def test_car_probability_matches_the_original(squeezenet):
    rgb = cv2.cvtColor(cv2.imread(str(CHECK_IMAGES / "car.png")), cv2.COLOR_BGR2RGB)
    p = softmax(squeezenet.run(cv2.resize(rgb, (227, 227))).logits)
    assert p[817] == pytest.approx(0.70, abs=0.05)


def test_graph_is_fp32_with_two_dynamic_outputs(models_dir, squeezenet):
    model = onnx.load(models_dir / MODEL_FILENAME)
    assert [o.name for o in model.graph.output] == ["fire9", "logits"]
    assert all(t.data_type == onnx.TensorProto.FLOAT for t in model.graph.initializer if t.name.endswith(".w"))
    manifest = json.loads((models_dir / MODEL_FILENAME).with_suffix(".json").read_text())
    assert manifest["n_conv_layers"] == 26 and manifest["precision"] == "fp32"
    # Convolutional up to the head: the fire9 map grows with the input.
    for h, w, fh, fw in [(224, 224, 13, 13), (227, 227, 14, 14), (448, 597, 27, 37)]:
        out = squeezenet.run(np.zeros((h, w, 3), np.uint8))
        assert out.fire9.shape == (fh, fw, 512)
        assert out.logits.shape == (1000,)


def test_wrong_folder_is_a_clear_error(tmp_path):
    with pytest.raises(ModelBuildError, match="no OpenVINO IR"):
        build_squeezenet_onnx(tmp_path, tmp_path / "x.onnx")
    (tmp_path / "a.xml").write_text("<net/>")
    (tmp_path / "a.bin").write_bytes(b"\0" * 10)
    with pytest.raises(ModelBuildError, match="float16 values"):
        build_squeezenet_onnx(tmp_path, tmp_path / "x.onnx")
