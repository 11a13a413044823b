"""The description file of a global model a user adds (``geoloc models add NAME --onnx FILE --spec SPEC``).

Why a file and not code: the strongest place-recognition descriptors (CosPlace, EigenPlaces, SALAD, BoQ,
MegaLoc) differ only in how their input is prepared and what their graph returns, so one small TOML or
JSON file says all a pipeline needs to run an exported ONNX graph: the input size and resize rule, the
colour order, the pixel range, mean and std, the tensor layout, the output (a global vector, or a feature
map to pool by GeM) and its dimension, and the licence the weights come under. The spec holds no name:
the name is given when the model is added, so one spec serves any number of copies.

A spec this module cannot read, or one that says something impossible, raises ``SpecRefused`` with the
reason; nothing is guessed.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path

from app.engine.errors import GeolocError

SPEC_FORMAT = 1
#: The resize rules (``input.resize``): how a photo becomes the graph's input.
#: ``short_side``: the short side scaled to ``size``, the aspect kept, the whole photo (the graph must take any
#: height and width); ``center_crop``: the same, then the centre ``size`` x ``size`` square; ``pad``: the long
#: side scaled to ``size``, then padded to a square with the mean colour; ``fixed``: stretched to ``size`` x
#: ``size``.
RESIZE_RULES = ("short_side", "center_crop", "pad", "fixed")
OUTPUT_KINDS = ("global", "feature_map")
LAYOUTS = ("nchw", "nhwc")
COLOURS = ("rgb", "bgr")
MAX_SIZE = 2048
MAX_DIM = 65536


class SpecRefused(GeolocError):
    """A model spec that cannot be read or says something impossible; the message says what and where."""


@dataclass(frozen=True)
class InputSpec:
    size: int
    resize: str = "short_side"
    colour: str = "rgb"
    #: The values the graph takes are in 0..``pixel_range`` before mean and std: 1.0 (PyTorch's
    #: ``ToTensor``) or 255.0 (Caffe and TensorFlow exports).
    pixel_range: float = 1.0
    #: Per channel, in the order the graph's channels come (after ``colour``).
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    layout: str = "nchw"
    #: The graph's input name; None: its only input.
    name: str | None = None


@dataclass(frozen=True)
class OutputSpec:
    #: ``global``: one descriptor per image, used as it is (L2-normalised); ``feature_map``: a (C, H, W) map
    #: (``layout``) GeM-pooled with ``gem_p`` into the descriptor, and sampled at keypoints by the hybrid.
    kind: str
    dim: int
    gem_p: float = 3.0
    #: The graph's output name; None: its first output.
    name: str | None = None


@dataclass(frozen=True)
class ModelSpec:
    input: InputSpec
    output: OutputSpec
    licence: str
    format: int = SPEC_FORMAT

    def to_json(self) -> str:
        """The canonical form stored beside the added model (what ``load_spec`` reads back)."""
        return json.dumps(asdict(self), indent=1, sort_keys=True) + "\n"


def load_spec(path: Path) -> ModelSpec:
    """Read a TOML (``.toml``) or JSON (any other name) spec."""
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise SpecRefused(f"the spec {path} cannot be read: {e.strerror or e}") from None
    try:
        text = raw.decode("utf-8")
        data = tomllib.loads(text) if Path(path).suffix.lower() == ".toml" else json.loads(text)
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, json.JSONDecodeError) as e:
        kind = "TOML" if Path(path).suffix.lower() == ".toml" else "JSON"
        raise SpecRefused(f"the spec {path} is not valid {kind}: {e}") from None
    return parse_spec(data)


def parse_spec(data: object) -> ModelSpec:
    """A spec from its parsed TOML or JSON; unknown keys are refused (a misspelt key would silently default)."""
    if not isinstance(data, dict):
        raise SpecRefused("a spec is a table of keys (input, output, licence)")
    _known(data, {"format", "input", "output", "licence", "license"}, "the spec")
    fmt = data.get("format", SPEC_FORMAT)
    if fmt != SPEC_FORMAT:
        raise SpecRefused(f"spec format {fmt!r} is not one this version reads (format = {SPEC_FORMAT})")
    licence = data.get("licence", data.get("license"))
    if not isinstance(licence, str) or not licence.strip() or "\n" in licence:
        raise SpecRefused("licence: one line saying under which licence the weights may be used")
    return ModelSpec(input=_input(data.get("input")), output=_output(data.get("output")), licence=licence.strip())


def _input(data: object) -> InputSpec:
    if not isinstance(data, dict):
        raise SpecRefused("input: a table with size, resize, colour, pixel_range, mean, std")
    _known(data, {"size", "resize", "colour", "color", "pixel_range", "mean", "std", "layout", "name"}, "input")
    size = data.get("size")
    if not isinstance(size, int) or isinstance(size, bool) or not 16 <= size <= MAX_SIZE:
        raise SpecRefused(f"input.size: a whole number of pixels from 16 to {MAX_SIZE}, not {size!r}")
    resize = _choice(data.get("resize", "short_side"), RESIZE_RULES, "input.resize")
    colour = _choice(data.get("colour", data.get("color", "rgb")), COLOURS, "input.colour")
    layout = _choice(data.get("layout", "nchw"), LAYOUTS, "input.layout")
    pixel_range = data.get("pixel_range", 1.0)
    if pixel_range not in (1, 255):
        raise SpecRefused(f"input.pixel_range: 1.0 (values 0..1) or 255.0 (values 0..255), not {pixel_range!r}")
    mean = _triple(data.get("mean", [0.0, 0.0, 0.0]), "input.mean")
    std = _triple(data.get("std", [1.0, 1.0, 1.0]), "input.std")
    if any(s <= 0 for s in std):
        raise SpecRefused(f"input.std: every value must be above 0, not {list(std)}")
    name = _optional_name(data.get("name"), "input.name")
    return InputSpec(size, resize, colour, float(pixel_range), mean, std, layout, name)


def _output(data: object) -> OutputSpec:
    if not isinstance(data, dict):
        raise SpecRefused("output: a table with kind (global or feature_map) and dim")
    _known(data, {"kind", "dim", "gem_p", "name"}, "output")
    kind = _choice(data.get("kind"), OUTPUT_KINDS, "output.kind")
    dim = data.get("dim")
    if not isinstance(dim, int) or isinstance(dim, bool) or not 1 <= dim <= MAX_DIM:
        raise SpecRefused(f"output.dim: the descriptor's (or map's channels') length, 1 to {MAX_DIM}, not {dim!r}")
    gem_p = data.get("gem_p", 3.0)
    if kind == "global" and "gem_p" in data:
        raise SpecRefused("output.gem_p: only a feature_map is pooled; a global output is used as it is")
    if not isinstance(gem_p, int | float) or isinstance(gem_p, bool) or not 1.0 <= gem_p <= 10.0:
        raise SpecRefused(f"output.gem_p: the GeM power, from 1 (average) to 10, not {gem_p!r}")
    return OutputSpec(kind, dim, float(gem_p), _optional_name(data.get("name"), "output.name"))


def _known(data: dict, keys: set[str], where: str) -> None:
    unknown = sorted(set(data) - keys)
    if unknown:
        raise SpecRefused(f"{where}: unknown keys {unknown}; known: {sorted(keys)}")


def _choice(value: object, choices: tuple[str, ...], where: str) -> str:
    if value not in choices:
        raise SpecRefused(f"{where}: one of {', '.join(choices)}, not {value!r}")
    return str(value)


def _triple(value: object, where: str) -> tuple[float, float, float]:
    ok = isinstance(value, list) and len(value) == 3
    ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    if not ok:
        raise SpecRefused(f"{where}: three finite numbers, one per channel, not {value!r}")
    return (float(value[0]), float(value[1]), float(value[2]))


def _optional_name(value: object, where: str) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise SpecRefused(f"{where}: the graph's tensor name, a non-empty string")
    return value


def spec_from_json(text: str) -> ModelSpec:
    """The stored canonical form (``ModelSpec.to_json``) read back."""
    data = json.loads(text)
    data["input"]["mean"] = list(data["input"]["mean"])
    data["input"]["std"] = list(data["input"]["std"])
    out = data["output"]
    if out.get("kind") == "global":
        out.pop("gem_p", None)
    return parse_spec(data)
