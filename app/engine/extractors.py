"""Local-feature extractors by name (after hloc's ``extractors/``): one small class per extractor, each
with its ``default_conf``, built here with the models dir.

Why a registry: a pipeline configuration names its extractor (``local="xfeat"``), and adding the next
learned extractor should touch its own module and one line here, not the pipeline. Handcrafted extractors
(``local_features``) need nothing; learned ones (``requires_model``) load their ONNX file from the models
dir, lazily, on first use.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from app.engine.errors import ModelNotReady
from app.engine.local_features import LocalFeatures, Orb, RootSift
from app.engine.models.xfeat import XFeatFeatures


class LocalExtractor(Protocol):
    default_conf: dict
    conf: dict

    @property
    def dim(self) -> int: ...

    def __call__(self, rgb: np.ndarray) -> LocalFeatures: ...


REGISTRY: dict[str, type] = {"sift": RootSift, "orb": Orb, "xfeat": XFeatFeatures}


def extractor_files(name: str) -> tuple[str, ...]:
    """Built files (relative to the models dir) the extractor ``name`` reads; none for handcrafted ones."""
    if name not in REGISTRY:
        raise ValueError(f"unknown local-feature extractor {name!r}; choose one of {', '.join(REGISTRY)}")
    return tuple(getattr(REGISTRY[name], "model_files", ()))


def build_extractor(name: str, models_dir: Path | None = None, **conf) -> LocalExtractor:
    """The extractor ``name`` with ``conf`` over its ``default_conf``."""
    try:
        cls = REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown local-feature extractor {name!r}; choose one of {', '.join(REGISTRY)}") from None
    if getattr(cls, "requires_model", False):
        if models_dir is None:
            raise ModelNotReady(f"the {name} extractor needs the models dir (its ONNX model lives there)")
        return cls(Path(models_dir), **conf)
    return cls(**conf)
