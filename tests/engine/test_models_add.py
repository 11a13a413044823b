"""`geoloc models add`: a plain ONNX export of one of the project's own models, described by a spec, is added
through the command and evaluates exactly as the built-in configuration; bad files and specs are refused
with the reason, and nothing is added.

The exports are real: the EfficientNet-Lite2 and SqueezeNet graphs our converters build, cut down to what a
user's ``torch.onnx.export`` gives (the preprocessing folded into them removed, so the spec must say it).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from tests.conftest import SHARED

PHOTOS_40 = SHARED / "manifests" / "penn-photos-40.csv"

LITE2_SPEC = """
licence = "Apache-2.0 (EfficientNet-Lite2 ImageNet weights, ml-illustrated/EfficientNet-Lite-PyTorch)"

[input]
size = 448
resize = "short_side"
colour = "rgb"
pixel_range = 255.0
mean = [127.0, 127.0, 127.0]
std = [128.0, 128.0, 128.0]

[output]
kind = "feature_map"
dim = 1280
gem_p = 3.0
"""


def geoloc(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "GEOLOC_ORT_THREADS": "1"}
    p = subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, env=env, timeout=900)
    if check and p.returncode != 0:
        raise AssertionError(f"geoloc {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def _strip_preprocessing(model: onnx.ModelProto, first_real_input: str, outputs: list[str]) -> onnx.ModelProto:
    """The graph from the tensor ``first_real_input`` (which becomes its input ``input``) to ``outputs``: the
    nodes before it (the preprocessing our converters fold in) and those no output needs are dropped."""
    g = model.graph
    dims = [d.dim_value or d.dim_param for d in g.input[0].type.tensor_type.shape.dim]
    needed, keep = set(outputs), []
    for node in reversed(g.node):  # walking back from the outputs, stopping at ``first_real_input``
        if set(node.output) & needed and first_real_input not in node.output:
            keep.append(node)
            needed |= set(node.input)
    keep.reverse()
    for n in keep:
        n.input[:] = ["input" if i == first_real_input else i for i in n.input]
    used = {i for n in keep for i in n.input}
    graph = helper.make_graph(
        keep,
        g.name,
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, dims)],
        [o for o in g.output if o.name in outputs],
        initializer=[t for t in g.initializer if t.name in used],
    )
    out = helper.make_model(graph, opset_imports=model.opset_import, ir_version=model.ir_version)
    onnx.checker.check_model(out)
    return out


def export_lite2_head(models_dir: Path, path: Path) -> Path:
    """lite2-gem's global branch as a plain export: RGB input already normalised, the 1280-channel head map."""
    from app.engine.models.efficientnet_lite import model_filename

    model = onnx.load(models_dir / model_filename(2))
    onnx.save(_strip_preprocessing(model, "input.norm", ["head"]), path)
    return path


def export_squeezenet_vector(models_dir: Path, path: Path, size: int = 224) -> tuple[Path, list[float]]:
    """SqueezeNet's fire9 average-pooled into a 512-d vector, for BGR input with the Caffe mean subtracted,
    at a fixed size x size: another input size, rule, colour order and normalisation, and a global output.
    Returns the path and the BGR mean the spec must give."""
    from app.engine.models.squeezenet import MODEL_FILENAME

    model = onnx.load(models_dir / MODEL_FILENAME)
    mean = next(t for t in model.graph.initializer if t.name == "mean_bgr")
    mean_bgr = onnx.numpy_helper.to_array(mean).reshape(-1).astype(float).tolist()
    plain = _strip_preprocessing(model, "data", ["fire9"])
    g = plain.graph
    g.node.extend(
        [
            helper.make_node("GlobalAveragePool", ["fire9"], ["pooled"]),
            helper.make_node("Flatten", ["pooled"], ["descriptor"], axis=1),
        ]
    )
    del g.output[:]
    g.output.append(helper.make_tensor_value_info("descriptor", TensorProto.FLOAT, [1, 512]))
    del g.input[:]
    g.input.append(helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 3, size, size]))
    onnx.checker.check_model(plain)
    onnx.save(plain, path)
    return path, mean_bgr


def squeezenet_spec(mean_bgr: list[float], size: int = 224, dim: int = 512) -> str:
    return json.dumps(
        {
            "licence": "BSD-2-Clause (SqueezeNet 1.1, forresti/SqueezeNet)",
            "input": {
                "size": size,
                "resize": "center_crop",
                "colour": "bgr",
                "pixel_range": 255.0,
                "mean": mean_bgr,
                "std": [1.0, 1.0, 1.0],
            },
            "output": {"kind": "global", "dim": dim, "name": "descriptor"},
        }
    )


def write_nan_onnx(path: Path) -> Path:
    """A tiny graph whose 3-d global output is NaN for every image: sqrt(-(|mean colour| + 1))."""
    graph = helper.make_graph(
        [
            helper.make_node("GlobalAveragePool", ["input"], ["pooled"]),
            helper.make_node("Flatten", ["pooled"], ["flat"], axis=1),
            helper.make_node("Abs", ["flat"], ["abs"]),
            helper.make_node("Add", ["abs", "one"], ["plus"]),
            helper.make_node("Neg", ["plus"], ["neg"]),
            helper.make_node("Sqrt", ["neg"], ["descriptor"]),
        ],
        "nan",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 3, None, None])],
        [helper.make_tensor_value_info("descriptor", TensorProto.FLOAT, [1, 3])],
        initializer=[onnx.numpy_helper.from_array(np.ones((1, 3), np.float32), "one")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


@pytest.fixture(scope="module")
def exports(tmp_path_factory, models_dir, lite2) -> Path:
    """The plain exports and their specs, and a models dir of this module's own holding the built-in
    EfficientNet-Lite2 (what lite2-gem runs) beside which models are added."""
    from app.engine.models.efficientnet_lite import model_filename

    d = tmp_path_factory.mktemp("models_add")
    export_lite2_head(models_dir, d / "lite2-head.onnx")
    (d / "lite2-head.toml").write_text(LITE2_SPEC)
    _, mean_bgr = export_squeezenet_vector(models_dir, d / "squeezenet-vector.onnx")
    (d / "squeezenet-vector.json").write_text(squeezenet_spec(mean_bgr))
    own = d / "models"
    own.mkdir()
    os.symlink(models_dir / model_filename(2), own / model_filename(2))
    return d


def _listing(models_dir: Path) -> list[str]:
    root = models_dir / "added"
    return sorted(p.name for p in root.iterdir()) if root.is_dir() else []


def test_models_add_refuses_with_the_reason_and_adds_nothing(exports, tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    not_onnx = tmp_path / "photo.onnx"
    not_onnx.write_bytes(b"\xff\xd8\xff\xe0 this is a JPEG header, not a graph" * 20)
    lite2_spec = exports / "lite2-head.toml"
    wrong_dim = tmp_path / "wrong-dim.toml"
    wrong_dim.write_text(LITE2_SPEC.replace("dim = 1280", "dim = 1000"))
    sq, sq_spec = exports / "squeezenet-vector.onnx", json.loads((exports / "squeezenet-vector.json").read_text())
    wrong_size = tmp_path / "wrong-size.json"
    wrong_size.write_text(json.dumps({**sq_spec, "input": {**sq_spec["input"], "size": 256}}))
    nan_spec = tmp_path / "nan.json"
    nan_spec.write_text(json.dumps({"licence": "MIT", "input": {"size": 64}, "output": {"kind": "global", "dim": 3}}))
    bad_spec = tmp_path / "bad.toml"
    bad_spec.write_text(LITE2_SPEC.replace('resize = "short_side"', 'resize = "squash"'))
    cases = [
        ("plain", not_onnx, lite2_spec, "photo.onnx is not an ONNX model"),
        ("dim", exports / "lite2-head.onnx", wrong_dim, "has 1280 channels: the spec declares 1000"),
        ("size", sq, wrong_size, "input size mismatch: the graph takes [1, 3, 224, 224] inputs, the spec says 256"),
        ("nan", write_nan_onnx(tmp_path / "nan.onnx"), nan_spec, "3 NaN or infinite values"),
        ("spec", exports / "lite2-head.onnx", bad_spec, "input.resize: one of short_side, center_crop, pad, fixed"),
        ("lite2-gem", exports / "lite2-head.onnx", lite2_spec, "'lite2-gem' is a built-in configuration's name"),
        ("squeezenet", sq, exports / "squeezenet-vector.json", "'squeezenet' is a built-in global model's name"),
        ("Bad Name", sq, exports / "squeezenet-vector.json", "is not one a configuration can carry"),
    ]
    for name, model, spec, reason in cases:
        p = geoloc(
            "models", "add", name, "--onnx", str(model), "--spec", str(spec), "--models-dir", str(models), check=False
        )
        assert p.returncode == 2, (name, p.stdout, p.stderr)
        assert reason in p.stderr, (name, p.stderr)
        assert _listing(models) == [], (name, _listing(models))  # no folder, no leftover temporary
    # A name taken by an added model: the first add succeeds, the second is refused and changes nothing.
    args = ["--onnx", str(sq), "--spec", str(exports / "squeezenet-vector.json"), "--models-dir", str(models)]
    geoloc("models", "add", "sq-vec", *args)
    before = (models / "added" / "sq-vec" / "SHA256SUMS").read_text()
    p = geoloc("models", "add", "sq-vec", *args[:2], "--spec", str(nan_spec), *args[4:], check=False)
    assert p.returncode == 2 and "a model named 'sq-vec' was added" in p.stderr, p.stderr
    assert _listing(models) == ["sq-vec"] and (models / "added" / "sq-vec" / "SHA256SUMS").read_text() == before


def test_models_add_list_and_check_verify_the_sha256(exports, tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    sq = exports / "squeezenet-vector.onnx"
    out = geoloc(
        "models",
        "add",
        "sqv",
        "--onnx",
        str(sq),
        "--spec",
        str(exports / "squeezenet-vector.json"),
        "--models-dir",
        str(models),
    )
    assert "added added model sqv (512-d global vector, center_crop 224 px)" in out.stdout, out.stdout
    assert "configurations: sqv, sqv-hybrid" in out.stdout
    folder = models / "added" / "sqv"
    assert sorted(p.name for p in folder.iterdir()) == ["SHA256SUMS", "model.onnx", "spec.json"]
    assert folder.joinpath("model.onnx").read_bytes() == sq.read_bytes()
    listed = geoloc("models", "list", "--models-dir", str(models), "--check", check=False)
    files = "added/sqv/model.onnx, added/sqv/spec.json, added/sqv/SHA256SUMS"
    assert f"added global model\tsqv\t{files}\tadded, sha256 verified" in listed.stdout, listed.stdout
    assert "configs sqv, sqv-hybrid; licence: BSD-2-Clause" in listed.stdout
    # A changed file is named by --check (exit 1).
    spec = json.loads(folder.joinpath("spec.json").read_text())
    spec["input"]["size"] = 225
    folder.joinpath("spec.json").write_text(json.dumps(spec))
    listed = geoloc("models", "list", "--models-dir", str(models), "--check", check=False)
    assert listed.returncode == 1 and "spec.json is not the file that was added" in listed.stderr, listed.stderr


def test_models_add_resize_rules_colour_and_layout_prepare_what_the_spec_says():
    from app.engine.configs import get_config
    from app.engine.model_add import probe_image
    from app.engine.model_spec import parse_spec
    from app.engine.models.spec_model import prepare

    rgb = probe_image((480, 640))
    base = {"licence": "MIT", "output": {"kind": "global", "dim": 8}}

    def spec(**inp):
        return parse_spec({**base, "input": {"size": 224, **inp}})

    assert prepare(rgb, spec(), 300).shape == (1, 3, 300, 400)  # short_side: the pipeline's size, aspect kept
    assert prepare(rgb, spec(resize="center_crop"), 300).shape == (1, 3, 224, 224)
    assert prepare(rgb, spec(resize="fixed", layout="nhwc"), 300).shape == (1, 224, 224, 3)
    padded = prepare(rgb, spec(resize="pad", mean=[0.5, 0.5, 0.5], std=[0.25, 0.25, 0.25]), 300)
    assert padded.shape == (1, 3, 224, 224) and not padded[0, :, :20].any() and padded[0, :, 112].any()
    x = prepare(rgb, spec(resize="fixed", pixel_range=255, colour="bgr"), 0)
    y = prepare(rgb, spec(resize="fixed", pixel_range=1.0), 0)
    assert np.allclose(x[0, ::-1] / 255.0, y[0], atol=1e-6)  # channel order reversed, 0..255 against 0..1
    # The built-in configurations keep the feature-cache keys they had.
    assert "global_pooling" not in get_config("lite2-gem").extraction_key()


def _recall(models: Path, config: str, out: Path) -> dict[str, float]:
    geoloc("eval", "--manifest", str(PHOTOS_40), "--config", config, "--models-dir", str(models), "--json", str(out))
    return json.loads(out.read_text())["recall_at"]


@pytest.mark.slow
def test_models_add_an_export_of_lite2_gem_recalls_as_the_built_in(exports, tmp_path):
    """The same R@1/5 as lite2-gem on the 40 whole photos, to the digit (and R@10/20 too)."""
    models = exports / "models"
    geoloc(
        "models",
        "add",
        "lite2-export",
        "--onnx",
        str(exports / "lite2-head.onnx"),
        "--spec",
        str(exports / "lite2-head.toml"),
        "--models-dir",
        str(models),
    )
    built_in = _recall(models, "lite2-gem", tmp_path / "built-in.json")
    added = _recall(models, "lite2-export", tmp_path / "added.json")
    print(f"lite2-gem {built_in}; lite2-export {added}")
    assert added == built_in
    assert built_in["1"] > 0.1  # a real recall, not two empty runs agreeing
