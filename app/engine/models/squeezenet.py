"""SqueezeNet 1.1 (ONNX), the default global model: its fire9 map (512 channels) is the dense map a pipeline
pools (GeM) and samples at keypoints (``app.engine.dense``).

The model follows the one ONNX lifecycle of ``app.engine.models.base`` (load under a lock, predict); this
module registers it (``squeezenet``, ``app.engine.registry``); ``app.engine.convert.squeezenet_onnx`` builds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.engine.dense import resize_short_side
from app.engine.models.base import OnnxModel
from app.engine.registry import Kind, Plugin, register

MODEL_FILENAME = "squeezenet1_1.onnx"
#: The graph's tensor names (the converter, ``app.engine.convert.squeezenet_onnx``, writes them).
INPUT_NAME = "image_rgb"
FIRE9_OUTPUT = "fire9"
LOGITS_OUTPUT = "logits"


@dataclass(frozen=True)
class CnnOutput:
    """fire9 as (H, W, 512) float32 and the 1000 logits of one image."""

    fire9: np.ndarray
    logits: np.ndarray
    input_hw: tuple[int, int]


class SqueezeNet(OnnxModel):
    """The built ONNX SqueezeNet."""

    filename = MODEL_FILENAME
    #: Channels of the dense map (fire9).
    dim = 512

    def run(self, rgb: np.ndarray) -> CnnOutput:
        """Run the net on an RGB uint8 image at its own size (resize first if you want another)."""
        x = np.ascontiguousarray(rgb.astype(np.float32).transpose(2, 0, 1)[None])
        fire9, logits = self.predict({INPUT_NAME: x}, [FIRE9_OUTPUT, LOGITS_OUTPUT])
        return CnnOutput(fire9=fire9[0].transpose(1, 2, 0), logits=logits[0], input_hw=rgb.shape[:2])

    def features(self, rgb: np.ndarray, short_side: int) -> CnnOutput:
        """Resize so the short side is ``short_side`` (aspect kept), then run."""
        return self.run(resize_short_side(rgb, short_side))

    def dense(self, rgb: np.ndarray, short_side: int) -> np.ndarray:
        """The global-model interface (``app.engine.models.base.GlobalModel``): fire9 as (H, W, 512)."""
        return self.features(rgb, short_side).fire9


def softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max())
    return e / e.sum()


register(Plugin(Kind.GLOBAL_MODEL, "squeezenet", lambda models_dir: SqueezeNet(models_dir / MODEL_FILENAME),
                (MODEL_FILENAME,), dim=SqueezeNet.dim))  # fmt: skip
