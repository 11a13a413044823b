"""Finishing and writing a graph our converters built, the same way for every model.

Why one place: every converter targets the same opset and IR version (readable by every onnxruntime released
since 2021), runs the full checker before anything is written, and writes through a temporary file and a
rename, so a build that dies half-way never leaves a truncated model that a server would then load.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import GraphProto, ModelProto, helper, numpy_helper

OPSET = 17
IR_VERSION = 8


def finish_model(graph: GraphProto) -> ModelProto:
    """The checked model of ``graph``; the checker's error is raised before anything is written."""
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="geoloc")
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model, full_check=True)
    return model


def save_model(model: ModelProto, path: Path) -> None:
    """Write ``model`` to ``path`` whole or not at all (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".onnx.tmp")
    onnx.save(model, tmp)
    tmp.replace(path)


class GraphBuilder:
    """Nodes and initializers of a graph being written, each node named after its output; a converter adds
    its own layers (a convolution with its folded BatchNorm, say) on top."""

    def __init__(self, state: dict[str, np.ndarray]):
        self.state = state
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []

    def init(self, name: str, value: np.ndarray) -> str:
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(value), name))
        return name

    def node(self, op: str, inputs: list[str], output: str, **attrs) -> str:
        self.nodes.append(helper.make_node(op, inputs, [output], name=output, **attrs))
        return output
