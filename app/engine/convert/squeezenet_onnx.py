"""Convert the pretrained SqueezeNet 1.1 (OpenVINO IR v6, FP16 Caffe weights) into an FP32 ONNX graph.

Why our own converter: no registry ships SqueezeNet weights and model hubs are unreachable, so the service
builds its model at set-up time from the copy in ../shared/models. The graph takes plain RGB pixels
(0..255, NCHW, any height and width) and folds the Caffe preprocessing (RGB->BGR swap, mean subtraction)
into its first nodes, so callers cannot get it wrong. It has two outputs: ``fire9`` (the last Fire module's
512-channel map, our local and global CNN descriptors) and ``logits`` (the 1000 ImageNet class scores,
used to check the conversion).
"""

from __future__ import annotations

import hashlib
import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from app.engine.convert.onnx_out import finish_model, save_model
from app.engine.errors import ModelBuildError, ModelNotReady
from app.engine.models.squeezenet import FIRE9_OUTPUT, INPUT_NAME, LOGITS_OUTPUT, MODEL_FILENAME
from app.engine.registry import ModelBuild, register_build

#: Per-channel mean the Caffe weights were trained with, in B, G, R order.
CAFFE_MEAN_BGR = (104.0, 117.0, 123.0)
#: The IR's weight file must end exactly at the last bias (NOTES.md): a cheap check against a wrong file.
EXPECTED_FP16_VALUES = 1_235_496


@dataclass
class _Layer:
    id: str
    name: str
    type: str
    data: dict[str, str]
    blobs: dict[str, tuple[int, int]]
    in_dims: dict[str, list[int]] = field(default_factory=dict)


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",")]


def _parse_ir(xml_path: Path) -> tuple[list[_Layer], dict[tuple[str, str], tuple[str, str]]]:
    """Return layers in file order and a map (to_layer, to_port) -> (from_layer, from_port)."""
    root = ET.parse(xml_path).getroot()
    layers: list[_Layer] = []
    for el in root.find("layers"):
        data_el = el.find("data")
        blobs = {}
        blobs_el = el.find("blobs")
        if blobs_el is not None:
            for b in blobs_el:
                blobs[b.tag] = (int(b.get("offset")), int(b.get("size")))
        in_dims = {}
        input_el = el.find("input")
        if input_el is not None:
            for port in input_el:
                in_dims[port.get("id")] = [int(d.text) for d in port.findall("dim")]
        layers.append(
            _Layer(
                id=el.get("id"),
                name=el.get("name"),
                type=el.get("type"),
                data=dict(data_el.attrib) if data_el is not None else {},
                blobs=blobs,
                in_dims=in_dims,
            )
        )
    edges = {}
    for e in root.find("edges"):
        edges[(e.get("to-layer"), e.get("to-port"))] = (e.get("from-layer"), e.get("from-port"))
    return layers, edges


def build_squeezenet_onnx(source_dir: Path, out_path: Path) -> dict:
    """Convert the IR in ``source_dir`` to ``out_path``; return the manifest written beside it."""
    xml_files = sorted(source_dir.glob("*.xml"))
    if not xml_files:
        raise ModelBuildError(
            f"no OpenVINO IR (.xml + .bin) in {source_dir}; point --from at the caffe-openvino-ir folder"
        )
    xml_path = xml_files[0]
    bin_path = xml_path.with_suffix(".bin")
    if not bin_path.exists():
        raise ModelBuildError(f"{bin_path} is missing")
    raw = bin_path.read_bytes()
    if len(raw) != 2 * EXPECTED_FP16_VALUES:
        raise ModelBuildError(
            f"{bin_path.name} holds {len(raw) // 2} float16 values, SqueezeNet 1.1 has {EXPECTED_FP16_VALUES}"
        )
    layers, edges = _parse_ir(xml_path)

    def blob(layer: _Layer, kind: str) -> np.ndarray:
        offset, size = layer.blobs[kind]
        return np.frombuffer(raw, dtype="<f2", count=size // 2, offset=offset).astype(np.float32)

    nodes: list[onnx.NodeProto] = []
    inits: list[onnx.TensorProto] = []
    out_name: dict[str, str] = {}  # layer id -> name of its output tensor

    def input_of(layer: _Layer, port: str) -> str:
        src_layer, _ = edges[(layer.id, port)]
        return out_name[src_layer]

    for layer in layers:
        t = layer.type
        if t == "Input":
            # Fold the Caffe preprocessing into the graph: RGB -> BGR, then subtract the mean.
            inits.append(numpy_helper.from_array(np.array([2, 1, 0], dtype=np.int64), "bgr_order"))
            mean = np.array(CAFFE_MEAN_BGR, dtype=np.float32).reshape(1, 3, 1, 1)
            inits.append(numpy_helper.from_array(mean, "mean_bgr"))
            nodes.append(helper.make_node("Gather", [INPUT_NAME, "bgr_order"], ["image_bgr"], axis=1))
            nodes.append(helper.make_node("Sub", ["image_bgr", "mean_bgr"], [layer.name]))
        elif t == "Convolution":
            d = layer.data
            in_ch = layer.in_dims["0"][1]
            out_ch = int(d["output"])
            kh, kw = _ints(d["kernel"])
            group = int(d.get("group", "1"))
            w = blob(layer, "weights").reshape(out_ch, in_ch // group, kh, kw)
            b = blob(layer, "biases")
            if b.shape != (out_ch,):
                raise ModelBuildError(f"{layer.name}: bias has {b.shape}, expected ({out_ch},)")
            inits += [numpy_helper.from_array(w, f"{layer.name}.w"), numpy_helper.from_array(b, f"{layer.name}.b")]
            nodes.append(
                helper.make_node(
                    "Conv",
                    [input_of(layer, "0"), f"{layer.name}.w", f"{layer.name}.b"],
                    [layer.name],
                    kernel_shape=[kh, kw],
                    strides=_ints(d["strides"]),
                    pads=_ints(d["pads_begin"]) + _ints(d["pads_end"]),
                    dilations=_ints(d.get("dilations", "1,1")),
                    group=group,
                )
            )
        elif t == "ReLU":
            nodes.append(helper.make_node("Relu", [input_of(layer, "0")], [layer.name]))
        elif t == "Pooling":
            d = layer.data
            if layer.name == "pool10" or d.get("pool-method") == "avg":
                # The IR fixes a 14x14 kernel (the 227 px case); global pooling works at any input size.
                nodes.append(helper.make_node("GlobalAveragePool", [input_of(layer, "0")], [layer.name]))
            else:
                nodes.append(
                    helper.make_node(
                        "MaxPool",
                        [input_of(layer, "0")],
                        [layer.name],
                        kernel_shape=_ints(d["kernel"]),
                        strides=_ints(d["strides"]),
                        pads=_ints(d["pads_begin"]) + _ints(d["pads_end"]),
                        ceil_mode=1 if d.get("rounding_type") == "ceil" else 0,
                    )
                )
        elif t == "Concat":
            ports = sorted((p for (lid, p) in edges if lid == layer.id), key=int)
            nodes.append(
                helper.make_node(
                    "Concat", [input_of(layer, p) for p in ports], [layer.name], axis=int(layer.data.get("axis", 1))
                )
            )
        elif t == "SoftMax":
            # We expose logits, not probabilities: flatten pool10's (N, 1000, 1, 1) output instead.
            nodes.append(helper.make_node("Flatten", [input_of(layer, "0")], [LOGITS_OUTPUT], axis=1))
            continue
        else:
            raise ModelBuildError(f"layer type {t} ({layer.name}) is not part of SqueezeNet 1.1")
        out_name[layer.id] = layer.name

    fire9 = next((lay for lay in layers if lay.name == "fire9/concat"), None)
    if fire9 is None or not any(n.output[0] == LOGITS_OUTPUT for n in nodes):
        raise ModelBuildError("the IR has no fire9/concat layer or no SoftMax head")
    nodes.append(helper.make_node("Identity", ["fire9/concat"], [FIRE9_OUTPUT]))

    graph = helper.make_graph(
        nodes,
        "squeezenet1_1",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["batch", 3, "height", "width"])],
        [
            helper.make_tensor_value_info(FIRE9_OUTPUT, TensorProto.FLOAT, ["batch", 512, "fh", "fw"]),
            helper.make_tensor_value_info(LOGITS_OUTPUT, TensorProto.FLOAT, ["batch", 1000]),
        ],
        initializer=inits,
    )
    model = finish_model(graph)
    save_model(model, out_path)
    manifest = {
        "model": "squeezenet1_1",
        "format": "onnx",
        "precision": "fp32",
        "source": str(source_dir.resolve()),
        "source_sha256": hashlib.sha256(raw).hexdigest(),
        "onnx_sha256": hashlib.sha256(out_path.read_bytes()).hexdigest(),
        "input": {"name": INPUT_NAME, "layout": "NCHW", "channels": "RGB", "range": "0..255"},
        "outputs": [FIRE9_OUTPUT, LOGITS_OUTPUT],
        "n_conv_layers": sum(1 for lay in layers if lay.type == "Convolution"),
        "onnx_version": onnx.__version__,
        "labels": [line.strip() for line in (source_dir / "squeezenet1.1.labels").read_text().splitlines()]
        if (source_dir / "squeezenet1.1.labels").exists()
        else None,
    }
    out_path.with_suffix(".json").write_text(json.dumps(manifest, indent=1))
    return manifest


def _build(models_dir: Path, source: Path | None, build_cache: Path) -> str:
    """``geoloc models build --only squeezenet --from IR_FOLDER``: our converter from the OpenVINO IR."""
    if source is None:
        raise ModelNotReady("building SqueezeNet needs the folder of its OpenVINO IR (--from)")
    manifest = build_squeezenet_onnx(source, models_dir / MODEL_FILENAME)
    return (
        f"wrote {models_dir / MODEL_FILENAME} ({manifest['n_conv_layers']} convolutions, "
        f"outputs {', '.join(manifest['outputs'])})"
    )


register_build(ModelBuild("squeezenet", (MODEL_FILENAME,), _build, source="from"))
