"""One lifecycle for every ONNX model (after immich's ``InferenceModel``): load under a lock, predict, unload.

Why one base: two requests may race to load a model, a missing file must say how to build it, and the
session options (threads, arena, spinning) must be the same for every model, so sessions are only ever
made by ``app.engine.models.ort.create_session``. A model subclass names its file and turns arrays into results.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import ClassVar, Protocol

import numpy as np

from app.engine.errors import ModelNotReady
from app.engine.models.ort import create_session


class OnnxModel:
    """A built ONNX file and its session, loaded on first use (or eagerly with ``load``)."""

    #: File name inside the models dir (``cls(models_dir / cls.filename)``).
    filename: ClassVar[str]

    def __init__(self, model_path: Path, intra_threads: int | None = None):
        self.model_path = Path(model_path)
        self.intra_threads = intra_threads
        self._session = None
        self._lock = threading.Lock()

    @classmethod
    def from_models_dir(cls, models_dir: Path, **kwargs) -> OnnxModel:
        return cls(Path(models_dir) / cls.filename, **kwargs)

    def load(self) -> None:
        """Idempotent and thread-safe: the first caller builds the session, the others wait for it."""
        with self._lock:
            if self._session is None:
                if not self.model_path.exists():
                    raise ModelNotReady(f"{self.model_path} is missing: run `geoloc models build` first")
                self._session = create_session(self.model_path, self.intra_threads)

    def unload(self) -> None:
        with self._lock:
            self._session = None

    @property
    def loaded(self) -> bool:
        return self._session is not None

    def signature(self) -> tuple[list[tuple[str, list]], list[tuple[str, list]]]:
        """The graph's inputs and outputs as (name, shape) pairs, a dimension None or a name where it is free
        (loading the graph first if needed): what a model checks a description of it against."""
        if self._session is None:
            self.load()

        def pairs(args) -> list[tuple[str, list]]:
            return [(a.name, [d if isinstance(d, int) else None for d in a.shape]) for a in args]

        return pairs(self._session.get_inputs()), pairs(self._session.get_outputs())

    def predict(self, inputs: dict[str, np.ndarray], outputs: list[str]) -> list[np.ndarray]:
        """Run the graph (loading it first if needed); onnxruntime sessions are safe to share across threads."""
        if self._session is None:
            self.load()
        return self._session.run(outputs, inputs)


class GlobalModel(Protocol):
    """A pretrained network that turns an image into a dense (H, W, C) feature map. A pipeline GeM-pools it
    into the global descriptor and samples it at keypoints for the feature-level hybrid
    (``app.engine.dense``), so a model only has to produce the map. Registered by name by its module
    (``app.engine.registry``, ``Kind.GLOBAL_MODEL``); a configuration names it (``PipelineConfig.global_model``)."""

    #: Channels of the dense map (the global descriptor's length before PCA).
    dim: int

    def load(self) -> None: ...

    def dense(self, rgb: np.ndarray, short_side: int) -> np.ndarray: ...
