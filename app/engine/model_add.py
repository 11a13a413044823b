"""Adding a user's ONNX global model with its spec (``geoloc models add NAME --onnx FILE --spec SPEC``).

Why check on add rather than at the first query: a graph exported with the wrong input size, a spec whose
dimension is wrong or weights that give NaN would otherwise be found by a fit an hour later, or by a
server that answers nonsense. So the copy that is to be added is loaded and run on probe images first
(the graph loads in onnxruntime, its input and output agree with the spec, each probe gives the declared
shape, finite values and the same output twice), and only a model that passes is moved into the models
dir, by one rename of a folder written beside it: a refusal (``ModelRefused``, with the reason) leaves
nothing behind.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine import configs, registry
from app.engine.added_models import (
    MODEL_FILE,
    NAME_PATTERN,
    SPEC_FILE,
    SUMS_FILE,
    added_root,
    describe,
    is_added,
    register_added_models,
    sha256_file,
    sums_text,
)
from app.engine.errors import GeolocError
from app.engine.model_spec import ModelSpec, load_spec
from app.engine.models.spec_model import SpecModel, SpecModelError, prepare
from app.engine.registry import Kind

#: Probe photos drawn here (landscape and portrait: a ``short_side`` graph must take both shapes).
PROBE_SHAPES = ((480, 640), (640, 480))


class ModelRefused(GeolocError):
    """The ONNX file or its spec cannot be added; the message says why. Nothing was added."""


class ModelNameTaken(ModelRefused):
    """The name is a built-in model's or configuration's, or a model was added under it already."""


@dataclass(frozen=True)
class AddedModel:
    name: str
    folder: Path
    sha256: str
    spec: ModelSpec
    configs: tuple[str, str]
    description: str
    probe_shape: tuple[int, ...]
    seconds: float


def probe_image(shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    """A deterministic RGB photo-like test card (gradients, blocks and noise): no file needed."""
    h, w = shape
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([xx / w * 255, yy / h * 255, (xx + yy) / (w + h) * 255], axis=-1)
    for _ in range(12):
        y, x = rng.integers(0, h - 40), rng.integers(0, w - 40)
        img[y : y + rng.integers(20, 120), x : x + rng.integers(20, 120)] = rng.integers(0, 256, 3)
    img += rng.normal(0, 12, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def check_name(name: str, models_dir: Path) -> None:
    """A name that is free: not a built-in global model's, not a configuration's (NAME or NAME-hybrid), not
    an added model's."""
    if not NAME_PATTERN.fullmatch(name):
        raise ModelRefused(
            f"the name {name!r} is not one a configuration can carry: lower-case letters, digits, '.', '-' and "
            "'_', starting with a letter, 48 characters at most"
        )
    register_added_models(models_dir)
    if (added_root(models_dir) / name).exists():
        raise ModelNameTaken(f"a model named {name!r} was added to {models_dir} already")
    if is_added(name):  # added to another models dir this process has read: free here
        return
    if name in registry.names(Kind.GLOBAL_MODEL):
        raise ModelNameTaken(f"{name!r} is a built-in global model's name: choose another")
    for taken in (name, f"{name}-hybrid"):
        if taken in configs.CONFIGS:
            raise ModelNameTaken(f"{taken!r} is a built-in configuration's name: choose another")


def check_graph(model: SpecModel) -> tuple[int, ...]:
    """Load the graph, check its input and output against the spec and run the probes; returns the shape of
    the first probe's output."""
    spec = model.spec
    try:
        model.load()
        inputs, outputs = model.signature()
    except Exception as e:  # onnxruntime's own errors: the file is not a graph it can run
        raise ModelRefused(f"onnxruntime cannot load the graph: {_first_line(e)}") from None
    _check_input(spec, inputs)
    out_names = [n for n, _ in outputs]
    if spec.output.name is not None and spec.output.name not in out_names:
        raise ModelRefused(f"the graph has no output {spec.output.name!r} (it has {', '.join(out_names)})")
    shape: tuple[int, ...] = ()
    for n, hw in enumerate(PROBE_SHAPES):
        x = prepare(probe_image(hw, seed=n), spec, spec.input.size)
        first = _run(model, x)
        if not np.isfinite(first).all():
            bad = int(np.size(first) - np.isfinite(first).sum())
            raise ModelRefused(f"the graph's output holds {bad} NaN or infinite values for a probe image")
        try:
            mapped = model.as_map(first)
        except SpecModelError as e:
            raise ModelRefused(str(e)) from None
        if n == 0:
            shape = tuple(first.shape)
            again = _run(model, x)
            if again.shape != first.shape or not np.allclose(again, first, rtol=1e-5, atol=1e-6):
                raise ModelRefused(
                    "the graph gives different outputs for the same probe image: it is not deterministic"
                )
        if not np.any(mapped):
            raise ModelRefused("the graph's output is all zeros for a probe image: it describes nothing")
    return shape


def _check_input(spec: ModelSpec, inputs: list[tuple[str, list]]) -> None:
    names = [n for n, _ in inputs]
    if spec.input.name is not None:
        if spec.input.name not in names:
            raise ModelRefused(f"the graph has no input {spec.input.name!r} (it has {', '.join(names)})")
        dims = dict(inputs)[spec.input.name]
    elif len(inputs) != 1:
        raise ModelRefused(f"the graph has {len(inputs)} inputs ({', '.join(names)}): name one in input.name")
    else:
        dims = inputs[0][1]
    if len(dims) != 4:
        raise ModelRefused(f"the graph's input has {len(dims)} dimensions: an image batch has 4 ({spec.input.layout})")
    channels, h, w = (dims[1], dims[2], dims[3]) if spec.input.layout == "nchw" else (dims[3], dims[1], dims[2])
    if dims[0] not in (None, 1) or channels not in (None, 3):
        raise ModelRefused(
            f"the graph's input is {_shape(dims)}: the spec's layout {spec.input.layout} needs a batch of 1 and "
            "3 colour channels there"
        )
    size = spec.input.size
    if spec.input.resize == "short_side":
        if h is not None or w is not None:
            raise ModelRefused(
                f"the graph takes {_shape(dims)} inputs only: resize short_side feeds whole photos of any aspect "
                f"(export it with free height and width, or use resize fixed or center_crop with size {h or w})"
            )
    elif (h is not None and h != size) or (w is not None and w != size):
        raise ModelRefused(
            f"input size mismatch: the graph takes {_shape(dims)} inputs, the spec says {size} x {size} "
            f"(resize {spec.input.resize})"
        )


def _run(model: SpecModel, x: np.ndarray) -> np.ndarray:
    try:
        return model.run(x)
    except Exception as e:  # onnxruntime refused the input or failed inside the graph
        raise ModelRefused(
            f"the graph fails on a probe image prepared by the spec (input {list(x.shape)}): {_first_line(e)}"
        ) from None


def _shape(dims: list) -> str:
    return "[" + ", ".join("?" if d is None else str(d) for d in dims) + "]"


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0][:300] if text else type(e).__name__


def _check_onnx(path: Path, given: Path) -> None:
    """``path`` (the copy) is an ONNX model the checker accepts; the reason names ``given``, the user's file."""
    import onnx

    try:
        onnx.checker.check_model(str(path))
    except Exception as e:  # protobuf's decode errors, the checker's: the file is not a usable ONNX model
        why = _first_line(e).replace(str(path), given.name)
        raise ModelRefused(f"{given} is not an ONNX model: {why}") from None


def add_model(name: str, onnx_path: Path, spec_path: Path, models_dir: Path) -> AddedModel:
    """Check ``onnx_path`` against the spec at ``spec_path`` and add both under ``name`` to ``models_dir``
    (``added/NAME/``), then register it. The copy is checked, not the source, so what was checked is what
    was added."""
    t0 = time.perf_counter()
    spec = load_spec(spec_path)  # SpecRefused says what is wrong with it
    check_name(name, models_dir)
    if not Path(onnx_path).is_file():
        raise ModelRefused(f"{onnx_path} is not a file")
    root = added_root(models_dir)
    root.mkdir(parents=True, exist_ok=True)
    work = root / f".adding-{name}-{os.getpid()}"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    try:
        shutil.copyfile(onnx_path, work / MODEL_FILE)
        (work / SPEC_FILE).write_text(spec.to_json())
        _check_onnx(work / MODEL_FILE, Path(onnx_path))
        model = SpecModel(work / MODEL_FILE, spec)
        shape = check_graph(model)
        model.unload()
        (work / SUMS_FILE).write_text(sums_text(work))
        _fsync_tree(work)
        target = root / name
        if target.exists():  # added meanwhile by another process
            raise ModelNameTaken(f"a model named {name!r} was added to {models_dir} meanwhile")
        os.rename(work, target)
        _fsync_dir(root)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    register_added_models(models_dir)
    return AddedModel(
        name=name,
        folder=target,
        sha256=sha256_file(target / MODEL_FILE),
        spec=spec,
        configs=(name, f"{name}-hybrid"),
        description=describe(name, spec),
        probe_shape=shape,
        seconds=time.perf_counter() - t0,
    )


def _fsync_tree(folder: Path) -> None:
    for path in folder.iterdir():
        with open(path, "rb") as f:
            os.fsync(f.fileno())
    _fsync_dir(folder)


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
