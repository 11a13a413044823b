"""Global models the user added (``geoloc models add``), registered as plug-ins beside the built-in ones.

Each lives in its own folder of the models dir, ``added/NAME/``: the ONNX graph (``model.onnx``), its spec
in canonical JSON (``spec.json``, ``app.engine.model_spec``) and the sha256 of both (``SHA256SUMS``, in
``sha256sum``'s format). ``register_added_models(models_dir)`` makes each one a global model of the
registry (``app.engine.registry``) under its name, and gives it the two named configurations NAME and
NAME-hybrid (``app.engine.configs.global_model_configs``).

Why registration takes the models dir: unlike a built-in, an added model is known only from the folder it
was added to, so whatever resolves a configuration name with a models dir at hand (a pipeline made or
loaded, a fit, an evaluation, a re-fit, a server's start) registers that folder's models first. It is
cheap (a listing and a small JSON file per model) and idempotent.
"""

from __future__ import annotations

import hashlib
import re
import threading
from dataclasses import dataclass
from pathlib import Path

from app.engine import configs, registry
from app.engine.model_spec import ModelSpec, SpecRefused, spec_from_json
from app.engine.models.spec_model import SpecModel
from app.engine.registry import Kind, Plugin

ADDED_DIR = "added"
MODEL_FILE = "model.onnx"
SPEC_FILE = "spec.json"
SUMS_FILE = "SHA256SUMS"
#: A name is a configuration name too (and NAME-hybrid): lower case, digits, dot, dash and underscore.
NAME_PATTERN = re.compile(r"[a-z][a-z0-9._-]{0,47}")

_lock = threading.Lock()
#: Names this module registered (so a second registration replaces its own, never a built-in).
_registered: dict[str, ModelSpec] = {}


def added_root(models_dir: Path) -> Path:
    return Path(models_dir) / ADDED_DIR


def files_of(name: str) -> tuple[str, ...]:
    """The added model's files, relative to the models dir (what Ray ships, what ``geoloc check`` verifies)."""
    return tuple(f"{ADDED_DIR}/{name}/{f}" for f in (MODEL_FILE, SPEC_FILE, SUMS_FILE))


def added_names(models_dir: Path) -> list[str]:
    """The models added to ``models_dir`` (folders with a spec; an add in progress is a dot-folder)."""
    root = added_root(models_dir)
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if NAME_PATTERN.fullmatch(p.name) and (p / SPEC_FILE).is_file())


def read_spec(models_dir: Path, name: str) -> ModelSpec:
    path = added_root(models_dir) / name / SPEC_FILE
    try:
        return spec_from_json(path.read_text())
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SpecRefused(f"{path} cannot be read as an added model's spec: {e}") from None


def describe(name: str, spec: ModelSpec) -> str:
    out = spec.output
    what = f"{out.dim}-d global vector" if out.kind == "global" else f"{out.dim}-channel map, GeM p={out.gem_p:g}"
    return f"added model {name} ({what}, {spec.input.resize} {spec.input.size} px)"


@dataclass(frozen=True)
class _Factory:
    """Builds the model from the models dir it is asked for (the spec is read from there, so a process that
    loads two models dirs reads each one's own)."""

    name: str

    def __call__(self, models_dir: Path) -> SpecModel:
        return SpecModel(added_root(models_dir) / self.name / MODEL_FILE, read_spec(models_dir, self.name))


def register_added_models(models_dir: Path | None) -> list[str]:
    """Register every model added to ``models_dir`` and its two configurations; returns their names. A name
    a built-in plug-in or configuration holds is left to the built-in (``geoloc models add`` refuses such
    names; this guards a built-in that came later)."""
    if models_dir is None:
        return []
    done = []
    with _lock:
        for name in added_names(models_dir):
            spec = read_spec(models_dir, name)
            ours = name in _registered
            if not ours and (name in registry.names(Kind.GLOBAL_MODEL) or _config_taken(name)):
                continue
            if _registered.get(name) != spec:
                plugin = Plugin(Kind.GLOBAL_MODEL, name, _Factory(name), files_of(name), dim=spec.output.dim)
                registry.register(plugin, replace=ours)
                for config in configs.global_model_configs(
                    name, spec.input.size, spec.output.gem_p, spec.output.kind == "global", describe(name, spec)
                ):
                    configs.register_config(config)
                _registered[name] = spec
            done.append(name)
    return done


def _config_taken(name: str) -> bool:
    return name in configs.CONFIGS or f"{name}-hybrid" in configs.CONFIGS


def is_added(name: str) -> bool:
    """Whether ``name`` is a global model this module registered (not a built-in)."""
    return name in _registered


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def sums_text(folder: Path) -> str:
    """``SHA256SUMS``'s content for a folder holding the model and its spec (``sha256sum -c`` reads it)."""
    return "".join(f"{sha256_file(folder / f)}  {f}\n" for f in (MODEL_FILE, SPEC_FILE))


def verify(models_dir: Path, name: str) -> list[str]:
    """What is wrong with an added model's files (missing, or not the sha256 recorded when it was added);
    empty when they are sound."""
    folder = added_root(models_dir) / name
    try:
        lines = (folder / SUMS_FILE).read_text().splitlines()
    except OSError:
        return [f"{folder / SUMS_FILE} is missing"]
    problems = []
    recorded = dict(reversed(line.split("  ", 1)) for line in lines if "  " in line)
    for f in (MODEL_FILE, SPEC_FILE):
        path = folder / f
        if f not in recorded:
            problems.append(f"{folder / SUMS_FILE} records no sha256 for {f}")
        elif not path.is_file():
            problems.append(f"{path} is missing")
        elif sha256_file(path) != recorded[f]:
            problems.append(f"{path} is not the file that was added (its sha256 differs from {SUMS_FILE}'s)")
    return problems
