"""The models a deployment runs: adding a user's ONNX global model, listing every model and checking their
files, and resolving a configuration name with the models dir at hand.

Why a use case: the CLI's ``geoloc models add``/``list`` and every face that takes a configuration name by
the side of a models dir (fit, eval, ingest, serve, refit, the first start) go through here, so a model
added to that dir is found the same way by all of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from app.engine.added_models import added_names, describe, files_of, read_spec, register_added_models, verify
from app.engine.configs import PipelineConfig, get_config
from app.engine.model_add import AddedModel
from app.engine.model_add import add_model as add_checked_model
from app.engine.registry import PLUGINS, Kind, names


def named_config(name: str, models_dir: Path | None) -> PipelineConfig:
    """The configuration ``name``: a built-in one, or one of a model added to ``models_dir``."""
    register_added_models(models_dir)
    return get_config(name)


def add_model(name: str, onnx_path: Path, spec_path: Path, models_dir: Path) -> AddedModel:
    """Check and add (``app.engine.model_add``): refused with the reason, and nothing added, unless the
    graph runs as the spec says."""
    return add_checked_model(name, Path(onnx_path), Path(spec_path), Path(models_dir))


@dataclass(frozen=True)
class ModelEntry:
    """One line of ``geoloc models list``."""

    kind: str
    name: str
    files: tuple[str, ...]
    #: ``built``, ``no files``, ``missing ...``; for an added model ``added, sha256 verified`` or what is wrong.
    state: str
    problems: tuple[str, ...] = ()
    about: str = ""


def list_models(models_dir: Path, verify_added: bool = False) -> list[ModelEntry]:
    """Every plug-in of the registry, then every added model; ``verify_added`` checks each added model's
    files against the sha256 recorded when it was added (reading them whole)."""
    added = set(register_added_models(models_dir))
    entries = []
    for kind in Kind:
        for name in names(kind):
            if kind == Kind.GLOBAL_MODEL and name in added:
                continue
            files = PLUGINS[kind][name].files
            gone = tuple(f for f in files if not (models_dir / f).is_file())
            state = "no files" if not files else f"missing {', '.join(gone)}" if gone else "built"
            entries.append(ModelEntry(str(kind), name, files, state, tuple(f"{f} is missing" for f in gone)))
    for name in added_names(models_dir):
        problems = tuple(verify(models_dir, name)) if verify_added else ()
        state = "added" + (", sha256 verified" if verify_added and not problems else "")
        if problems:
            state = "added, damaged: " + "; ".join(problems)
        spec = read_spec(models_dir, name)
        about = f"{describe(name, spec)}; configs {name}, {name}-hybrid; licence: {spec.licence}"
        entries.append(ModelEntry("added global model", name, files_of(name), state, problems, about))
    return entries


def check_models(models_dir: Path, config: PipelineConfig) -> list[str]:
    """Problems with the added model ``config`` runs on, if it runs on one (files missing or changed since
    they were added); built-in models are checked by loading them."""
    if config.uses_global_model and config.global_model in added_names(models_dir):
        return verify(models_dir, config.global_model)
    return []
