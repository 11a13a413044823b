"""What a pipeline does with any global model's dense feature map: GeM pooling into one global descriptor,
and bilinear sampling at local keypoints (the feature-level hybrid).

Why apart from the models: these are the pipeline's choices, not the model's, so a new global model
(``app.engine.registry``) only has to produce an (H, W, C) map and gets pooling and sampling free.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.engine.imageio import MAX_INPUT_ASPECT


def resize_short_side(rgb: np.ndarray, short_side: int) -> np.ndarray:
    """Scale so the short side is ``short_side``, within ``MAX_INPUT_ASPECT`` x ``short_side`` on the long."""
    h, w = rgb.shape[:2]
    s = min(short_side / min(h, w), MAX_INPUT_ASPECT * short_side / max(h, w))
    size = (max(1, round(w * s)), max(1, round(h * s)))
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
    return cv2.resize(rgb, size, interpolation=interp)


def gem_pool(fire9: np.ndarray, p: float = 3.0) -> np.ndarray:
    """Generalised-mean pooling of an (H, W, C) ReLU map, L2-normalised: the global CNN descriptor."""
    x = np.maximum(fire9.reshape(-1, fire9.shape[-1]), np.float32(1e-6), dtype=np.float32)
    # The default p = 3 as two float32 products summed in float64: np.power over a float64 copy of a
    # 720-channel map cost several times as much per query, and the descriptor moves by float32 rounding only.
    powered = x * x * x if p == 3 else np.power(x.astype(np.float64), p)
    g = np.power(powered.sum(axis=0, dtype=np.float64) / len(x), 1.0 / p)
    return (g / max(np.linalg.norm(g), 1e-12)).astype(np.float32)


def unit_vector(dense: np.ndarray, p: float = 3.0) -> np.ndarray:
    """A (1, 1, C) map that is already a global descriptor (a model with its own pooling head), L2-normalised:
    GeM would clamp its negative components."""
    if dense.shape[0] * dense.shape[1] != 1:
        raise ValueError(f"a global vector is a (1, 1, C) map, not {dense.shape}")
    g = dense.reshape(-1).astype(np.float64)
    return (g / max(np.linalg.norm(g), 1e-12)).astype(np.float32)


#: How a pipeline turns a global model's map into its global descriptor (``PipelineConfig.global_pooling``).
POOLINGS = {"gem": gem_pool, "none": unit_vector}


def pool(dense: np.ndarray, pooling: str, p: float) -> np.ndarray:
    return POOLINGS[pooling](dense, p)


def sample_at(fire9: np.ndarray, xy_norm: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Bilinear sample of the (H, W, C) map at positions ``xy_norm`` (N, 2), given as fractions of the
    image width and height (0..1), so the local-feature and CNN image sizes need not agree.
    Returns (N, C) float32, written into ``out`` when given; map cells are taken to cover the image evenly."""
    fh, fw, c = fire9.shape
    if len(xy_norm) == 0:
        return np.zeros((0, c), np.float32) if out is None else out
    gx = np.clip(xy_norm[:, 0] * fw - 0.5, 0, fw - 1)
    gy = np.clip(xy_norm[:, 1] * fh - 0.5, 0, fh - 1)
    x0 = np.floor(gx).astype(np.intp)
    y0 = np.floor(gy).astype(np.intp)
    x1 = np.minimum(x0 + 1, fw - 1)
    y1 = np.minimum(y0 + 1, fh - 1)
    # float32 weights and rows gathered from the flat map: the float64 promotion and the 2-D fancy indexing
    # were most of this stage's time (its result differs from the float64 way by float32 rounding only).
    ax = (gx - x0).astype(np.float32)[:, None]
    ay = (gy - y0).astype(np.float32)[:, None]
    flat = fire9.reshape(fh * fw, c)
    if flat.dtype != np.float32:
        flat = flat.astype(np.float32)
    if out is None:
        out = np.empty((len(xy_norm), c), np.float32)
    np.multiply(flat[y0 * fw + x0], (1 - ax) * (1 - ay), out=out)
    out += flat[y0 * fw + x1] * (ax * (1 - ay))
    out += flat[y1 * fw + x0] * ((1 - ax) * ay)
    out += flat[y1 * fw + x1] * (ax * ay)
    return out


def join_sampled(local: np.ndarray, dense: np.ndarray, xy_norm: np.ndarray, weight: float) -> np.ndarray:
    """The feature-level hybrid's descriptors: each unit local descriptor followed by ``weight`` times the unit
    map vector sampled at its keypoint, (N, D + C) float32.

    Written into one array in place: normalising and stacking copies took half of this stage's time with a
    720-channel map."""
    n, d = local.shape
    out = np.empty((n, d + dense.shape[-1]), np.float32)
    out[:, :d] = local
    sample_at(dense, xy_norm, out=out[:, d:])
    for part, scale in ((out[:, :d], 1.0), (out[:, d:], weight)):
        norms = np.sqrt(np.einsum("ij,ij->i", part, part))
        part *= np.divide(scale, norms, out=np.zeros_like(norms), where=norms > 0)[:, None]
    return out
