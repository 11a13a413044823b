"""The extractor registry and XFeat inside the pipeline: names, configuration, fit/save/load, the hybrid."""

import numpy as np
import pytest

from app.engine.configs import get_config
from app.engine.errors import ModelNotReady
from app.engine.imageio import load_image
from app.engine.local_features import RootSift
from app.engine.models.xfeat import XFeatFeatures
from app.engine.pipeline import Pipeline, load_pipeline, pipeline_dir
from app.engine.registry import Kind, UnknownModel, create, files_for, names
from app.manifests import read_manifest
from tests.conftest import penn_photo


@pytest.fixture(scope="module")
def rgb():
    return load_image(penn_photo("img_00000.jpg").read_bytes()).rgb


def build_extractor(name, models_dir=None, **conf):
    return create(Kind.LOCAL_EXTRACTOR, name, models_dir, **conf)


def test_registry_builds_each_extractor_with_its_default_conf(models_dir, xfeat):
    assert set(names(Kind.LOCAL_EXTRACTOR)) == {"sift", "orb", "xfeat"}
    assert files_for(get_config("orb-mbvlad-bin")) == [] and files_for(get_config("xfeat-mbvlad")) == ["xfeat.onnx"]
    sift = build_extractor("sift", max_keypoints=300)
    assert isinstance(sift, RootSift) and sift.conf == {"max_keypoints": 300, "long_side": 640}
    xf = build_extractor("xfeat", models_dir, long_side=480)
    assert isinstance(xf, XFeatFeatures) and xf.dim == 64
    assert xf.conf == {**XFeatFeatures.default_conf, "long_side": 480}
    with pytest.raises(ModelNotReady, match="models dir"):
        build_extractor("xfeat")
    with pytest.raises(UnknownModel, match="unknown local extractor 'superpoint'; registered: sift, orb, xfeat"):
        build_extractor("superpoint")


def test_xfeat_extractor_positions_are_fractions_of_the_image(models_dir, xfeat, rgb):
    f = build_extractor("xfeat", models_dir, max_keypoints=500, long_side=640)(rgb)
    assert len(f) == 500 and f.descriptors.shape == (500, 64) and f.descriptors.dtype == np.float32
    assert (f.xy >= 0).all() and (f.xy < 1).all()
    # Spread over the photo, not stuck in one corner (a wrong scale-back would squeeze them).
    assert f.xy[:, 0].max() > 0.9 and f.xy[:, 1].max() > 0.9


def test_missing_model_file_says_how_to_build_it(tmp_path, rgb):
    with pytest.raises(ModelNotReady, match="geoloc models build"):
        build_extractor("xfeat", tmp_path)(rgb)


@pytest.mark.parametrize("name", ["xfeat-mbvlad", "hybrid-xfeat"])
def test_xfeat_configurations_fit_save_and_load(name, mini_manifest, squeezenet, models_dir, xfeat, tmp_path):
    cfg = get_config(name).with_overrides({"k": 8, "max_keypoints": 400})
    rows = [r for r in read_manifest(mini_manifest) if r.split != "query"][:12]
    pipe = Pipeline(cfg, global_model=squeezenet, models_dir=models_dir)
    feats = [pipe.extract(load_image(r.image.read_bytes()).rgb) for r in rows]
    dim = 64 + (512 if cfg.cnn_local_weight > 0 else 0)
    assert all(f.local.shape == (400, dim) for f in feats)
    assert "local_features" in feats[0].timings_ms
    pipe.fit(feats, seed=0)
    a = pipe.encode_features(feats[0]).float_
    assert a.shape == (pipe.float_dim,) and np.linalg.norm(a) == pytest.approx(1, abs=1e-5)
    # The overridden name is not a registered configuration: save and reload under the base name.
    base = Pipeline(get_config(name), global_model=squeezenet, models_dir=models_dir)
    base.codebook, base.pca, base.manifest = pipe.codebook, pipe.pca, pipe.manifest
    base.save(tmp_path)
    loaded = Pipeline.load(tmp_path, squeezenet, models_dir)
    assert np.array_equal(loaded.encode_features(feats[0]).float_, base.encode_features(feats[0]).float_)
    with pytest.raises(ModelNotReady):
        Pipeline(get_config(name), global_model=squeezenet)  # no models dir: XFeat cannot be built
    # A service loads every model at start-up: a models dir without the ONNX files fails there.
    empty = tmp_path / "empty-models"
    base.save(pipeline_dir(empty, name))
    with pytest.raises(ModelNotReady, match="is missing"):
        load_pipeline(empty, name)


def test_existing_configurations_are_unchanged():
    """Fitted pipelines refuse to load under a changed definition: adding XFeat must not touch these."""
    assert get_config("hybrid").local == "sift" and get_config("hybrid").max_keypoints == 1000
    assert get_config("hybrid").model_dump()["local_long_side"] == 640
    assert get_config("sift-mbvlad").local == "sift" and get_config("orb-mbvlad-bin").local == "orb"
