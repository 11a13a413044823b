"""A global model described by a spec (``app.engine.model_spec``) rather than by a module of its own: the ONNX
graph a user exported, run the way its spec says.

Why one class for every such model: what tells CosPlace from MegaLoc at run time is only the input's
preparation and the output's shape, which the spec holds; so a model added with ``geoloc models add`` needs
no code. This module registers nothing itself: ``app.engine.added_models`` registers each added model by
the name it was added under.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from app.engine.dense import resize_short_side
from app.engine.errors import IncompatibleArtifact
from app.engine.model_spec import ModelSpec
from app.engine.models.base import OnnxModel


class SpecModelError(IncompatibleArtifact):
    """The graph's output is not what its spec declares (shape or channels): the added files were changed
    since ``geoloc models add`` checked them."""


def prepare(rgb: np.ndarray, spec: ModelSpec, short_side: int) -> np.ndarray:
    """An RGB uint8 photo as the graph's input tensor (batch of one), by the spec's resize rule, colour order,
    pixel range, mean, std and layout. ``short_side`` is the ``short_side`` rule's size (the pipeline's
    ``cnn_short_side``); the other rules take the spec's size, which a graph of fixed input size needs."""
    inp = spec.input
    size = inp.size
    if inp.resize == "short_side":
        img = resize_short_side(rgb, short_side)
    elif inp.resize == "center_crop":
        img = resize_short_side(rgb, size)
        h, w = img.shape[:2]
        top, left = max(0, (h - size) // 2), max(0, (w - size) // 2)
        img = img[top : top + size, left : left + size]
        if img.shape[:2] != (size, size):  # a photo beyond the resize's aspect bound: stretch the rest
            img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    elif inp.resize == "pad":
        h, w = rgb.shape[:2]
        s = size / max(h, w)
        nw, nh = max(1, round(w * s)), max(1, round(h * s))
        img = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    else:  # fixed
        h, w = rgb.shape[:2]
        interp = cv2.INTER_AREA if size < min(h, w) else cv2.INTER_LINEAR
        img = cv2.resize(rgb, (size, size), interpolation=interp)
    if inp.colour == "bgr":
        img = img[..., ::-1]
    x = img.astype(np.float32)
    if inp.pixel_range != 255.0:
        x *= np.float32(inp.pixel_range / 255.0)
    x = (x - np.asarray(inp.mean, np.float32)) / np.asarray(inp.std, np.float32)
    if inp.resize == "pad":  # the padding is the mean colour: zero after normalisation
        padded = np.zeros((size, size, 3), np.float32)
        top, left = (size - x.shape[0]) // 2, (size - x.shape[1]) // 2
        padded[top : top + x.shape[0], left : left + x.shape[1]] = x
        x = padded
    if inp.layout == "nchw":
        x = x.transpose(2, 0, 1)
    return np.ascontiguousarray(x[None])


class SpecModel(OnnxModel):
    """An added model's graph and spec: ``dense`` gives its feature map as (H, W, C), or for a ``global``
    output its descriptor as a (1, 1, D) map, which the pipeline takes as it is (``global_pooling="none"``)."""

    def __init__(self, model_path: Path, spec: ModelSpec, intra_threads: int | None = None):
        super().__init__(model_path, intra_threads)
        self.spec = spec
        self.dim = spec.output.dim
        self._io: tuple[str, str] | None = None

    def io_names(self) -> tuple[str, str]:
        """The input and output tensor names: the spec's, else the graph's only input and its first output."""
        if self._io is None:
            inputs, outputs = self.signature()
            self._io = (
                self.spec.input.name or inputs[0][0],
                self.spec.output.name or outputs[0][0],
            )
        return self._io

    def run(self, x: np.ndarray) -> np.ndarray:
        """The graph's raw output for one prepared input (``prepare``)."""
        input_name, output_name = self.io_names()
        (out,) = self.predict({input_name: x}, [output_name])
        return out

    def dense(self, rgb: np.ndarray, short_side: int) -> np.ndarray:
        """The global-model interface (``app.engine.models.base.GlobalModel``)."""
        return self.as_map(self.run(prepare(rgb, self.spec, short_side)))

    def as_map(self, out: np.ndarray) -> np.ndarray:
        """A raw output as the (H, W, C) map a pipeline reads, checked against the spec."""
        out_spec = self.spec.output
        if out_spec.kind == "global":
            if out.ndim == 0 or out.shape[0] != 1 or out.size != out_spec.dim:
                raise SpecModelError(
                    f"the graph's output has shape {list(out.shape)}: the spec declares one {out_spec.dim}-d "
                    f"global vector (shape [1, {out_spec.dim}])"
                )
            return np.ascontiguousarray(out.reshape(1, 1, out_spec.dim), dtype=np.float32)
        if out.ndim != 4 or out.shape[0] != 1:
            raise SpecModelError(
                f"the graph's output has shape {list(out.shape)}: the spec declares a feature map "
                f"(a batch of one, 4 dimensions, {self.spec.input.layout})"
            )
        fmap = out[0].transpose(1, 2, 0) if self.spec.input.layout == "nchw" else out[0]
        if fmap.shape[-1] != out_spec.dim:
            raise SpecModelError(
                f"the graph's feature map has {fmap.shape[-1]} channels: the spec declares {out_spec.dim}"
            )
        return np.ascontiguousarray(fmap, dtype=np.float32)
