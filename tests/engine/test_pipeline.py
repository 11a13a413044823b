"""The composed pipeline on real photos: fit, encode, save/load, and recognition of a re-encoded photo."""

import io

import numpy as np
import pytest
from PIL import Image

from app.domain import LocateOptions
from app.engine.configs import get_config
from app.engine.errors import IncompatibleArtifact, ModelNotReady
from app.engine.imageio import load_image
from app.engine.index.references import ReferenceIndex
from app.engine.pipeline import Pipeline
from app.evaluation.evaluate import RowReferences
from app.manifests import read_manifest
from app.usecases.locate import locate_features


@pytest.fixture(scope="module")
def images(mini_manifest):
    rows = [r for r in read_manifest(mini_manifest) if r.split != "query"]
    return rows, [load_image(r.image.read_bytes()).rgb for r in rows]


@pytest.mark.parametrize("name", ["sift-mbvlad", "hybrid-bin", "orb-mbvlad-bin", "squeezenet-gem"])
def test_fit_save_load_gives_identical_codes(name, images, squeezenet, tmp_path):
    rows, rgbs = images
    pipe = Pipeline(get_config(name), global_model=squeezenet)
    feats = [pipe.extract(x) for x in rgbs]
    pipe.fit(feats, seed=0)
    pipe.save(tmp_path)
    loaded = Pipeline.load(tmp_path, squeezenet)
    assert loaded.fingerprint == pipe.fingerprint
    a, b = pipe.encode_features(feats[0]), loaded.encode_features(feats[0])
    for x, y in ((a.float_, b.float_), (a.binary, b.binary)):
        assert (x is None and y is None) or np.array_equal(x, y)
    if a.float_ is not None:
        assert a.float_.shape == (pipe.float_dim,) and np.linalg.norm(a.float_) == pytest.approx(1, abs=1e-5)
    if a.binary is not None:
        assert a.binary.dtype == np.uint8 and len(a.binary) * 8 == pipe.bits


def test_a_reencoded_reference_is_found_first(images, squeezenet):
    """A reference photo, downscaled and re-compressed, comes back as the top candidate."""
    rows, rgbs = images
    pipe = Pipeline(get_config("hybrid"), global_model=squeezenet)
    feats = [pipe.extract(x) for x in rgbs]
    pipe.fit(feats, seed=0)
    index = ReferenceIndex(pipe.config, pipe.float_dim, pipe.bits)
    codes = [pipe.encode_features(f) for f in feats]
    index.add(np.arange(len(rows)), np.stack([c.float_ for c in codes]), None)
    refs = RowReferences(rows, list(range(len(rows))))
    photo = next(i for i, r in enumerate(rows) if "photos" in str(r.image))
    buf = io.BytesIO()
    Image.fromarray(rgbs[photo]).resize((800, 600) if rgbs[photo].shape[1] > rgbs[photo].shape[0] else (600, 800)).save(
        buf, "JPEG", quality=70
    )
    res = locate_features(pipe, index, refs, pipe.extract(load_image(buf.getvalue()).rgb), LocateOptions(top_k=5))
    assert res.candidates[0].reference_id == photo
    assert res.features_extracted > 100 and res.features_kept == res.features_extracted
    assert {"local_features", "cnn", "aggregate", "codes", "search", "estimate"} <= set(res.timings_ms)


def test_loading_needs_a_fit_and_the_same_definition(tmp_path, squeezenet, images):
    with pytest.raises(ModelNotReady):
        Pipeline.load(tmp_path, squeezenet)
    rows, rgbs = images
    pipe = Pipeline(get_config("sift-mbvlad").with_overrides({"k": 8}), global_model=None)
    pipe.fit([pipe.extract(x) for x in rgbs[:6]])
    pipe.save(tmp_path)
    with pytest.raises(Exception, match="unknown configuration|older definition"):
        Pipeline.load(tmp_path, None)


def test_a_config_that_needs_the_cnn_refuses_to_start_without_it():
    with pytest.raises(ModelNotReady):
        Pipeline(get_config("hybrid"), global_model=None)
    _ = IncompatibleArtifact
