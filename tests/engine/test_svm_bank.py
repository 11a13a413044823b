"""The SVM bank: labels on a constructed case, persistence across processes, the floor."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from app.engine.imageio import load_image
from app.engine.local_features import RootSift
from app.engine.svm_bank import BankParams, SvmBank, label_features
from app.engine.training.svm_training import negative_radius
from tests.conftest import PENN


def _pattern(size: int = 220) -> np.ndarray:
    """A distinctive synthetic texture (the 'billboard' that appears all over town)."""
    rng = np.random.default_rng(7)
    img = np.full((size, size, 3), 255, np.uint8)
    for _ in range(40):
        x, y = rng.integers(0, size, 2)
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        if rng.random() < 0.5:
            cv2.rectangle(
                img, (int(x), int(y)), (int(x + rng.integers(10, 60)), int(y + rng.integers(10, 60))), colour, -1
            )
        else:
            cv2.circle(img, (int(x), int(y)), int(rng.integers(5, 30)), colour, -1)
    return img


def _photo(name: str) -> np.ndarray:
    return load_image((PENN / "photos" / name).read_bytes()).rgb


def _paste(rgb: np.ndarray, patch: np.ndarray, x: int, y: int) -> np.ndarray:
    out = cv2.resize(rgb, (640, 480) if rgb.shape[1] > rgb.shape[0] else (480, 640))
    out = out.copy()
    out[y : y + patch.shape[0], x : x + patch.shape[1]] = patch
    return out


def _pattern_scene(extractor):
    """A photo with a pattern pasted in, the same place without it, and two far-away photos carrying the same
    pattern: the training photo's features, their labels, which of them lie on the pattern, and the far-away
    photos' descriptors."""
    patch = _pattern()
    train_img = _paste(_photo("img_00000.jpg"), patch, 40, 40)
    positive = cv2.resize(_photo("img_00000.jpg"), (train_img.shape[1], train_img.shape[0]))  # same place, no pattern
    confusers = [_paste(_photo(n), patch, 200, 150) for n in ("img_00050.jpg", "img_00090.jpg")]
    f = extractor(train_img)
    far = [extractor(c).descriptors for c in confusers]
    labels = label_features(f.descriptors, [extractor(positive).descriptors], far, BankParams(kind="contrastive"))
    h, w = train_img.shape[:2]
    px, py = f.xy[:, 0] * w, f.xy[:, 1] * h
    return f, labels, (px > 45) & (px < 255) & (py > 45) & (py < 255), far


def test_a_pattern_seen_at_far_away_places_is_labelled_negative():
    f, labels, on_pattern, far = _pattern_scene(RootSift(max_keypoints=1500, long_side=640))
    assert on_pattern.sum() > 30
    assert (labels[on_pattern] == -1).mean() > 0.7  # the pasted pattern: confusing
    assert (labels[~on_pattern] == 1).mean() > 0.5  # the building: matches the right place
    assert (labels[~on_pattern] == -1).mean() < 0.1

    conf = label_features(
        f.descriptors,
        [],
        far,
        BankParams(kind="confusers", confuser_quantile=0.93),
    )
    assert (conf[on_pattern] == -1).mean() > 0.7 and (conf[~on_pattern] == 1).mean() > 0.9


def _synthetic(n=3000, d=16, seed=0):
    """Two appearance clusters; in each, one direction separates useful from confusing features."""
    rng = np.random.default_rng(seed)
    centres = np.stack([np.eye(d)[0] * 4, np.eye(d)[1] * 4])
    x = np.vstack([c + rng.normal(size=(n // 2, d)) for c in centres]).astype(np.float32)
    y = np.where(x[:, 2] + 0.3 * rng.normal(size=n) > 0, 1, -1).astype(np.int8)
    return x, y


def test_bank_learns_and_survives_a_fresh_process(tmp_path):
    x, y = _synthetic()
    bank = SvmBank.train(x, y, BankParams(n_clusters=2, hard_rounds=3, C=1.0))
    acc = np.mean(np.sign(bank.decision(x)) == y)
    assert acc > 0.85
    assert all(c["train_accuracy"] > 0.8 for c in bank.manifest["clusters"])
    bank.threshold, bank.min_keep = 0.25, 10
    bank.save(tmp_path)
    np.save(tmp_path / "x.npy", x[:200])
    code = (
        "import sys, numpy as np; from pathlib import Path; from app.engine.svm_bank import SvmBank; "
        "d = Path(sys.argv[1]); b = SvmBank.load(d); x = np.load(d / 'x.npy'); "
        "np.save(d / 'dec.npy', b.decision(x)); np.save(d / 'keep.npy', b.keep(x))"
    )
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], check=True)
    assert np.array_equal(np.load(tmp_path / "dec.npy"), bank.decision(x[:200]))
    assert np.array_equal(np.load(tmp_path / "keep.npy"), bank.keep(x[:200]))
    again = SvmBank.load(tmp_path)
    assert again.threshold == 0.25 and again.min_keep == 10 and again.params.n_clusters == 2


def test_the_floor_holds_when_every_feature_scores_low():
    x, y = _synthetic()
    bank = SvmBank.train(x, y, BankParams(n_clusters=2))
    bank.threshold, bank.min_keep = 1e6, 50
    keep = bank.keep(x[:300])
    assert keep.sum() == 50
    d = bank.decision(x[:300])
    assert d[keep].min() >= d[~keep].max()  # the best-scored ones make up the floor
    assert bank.keep(x[:20]).sum() == 20  # fewer features than the floor: all of them
    neg = bank.keep(x[:300], "negative")
    bank.threshold = 0.0
    assert not (bank.keep(x[:300], "positive") & bank.keep(x[:300], "negative")).any()
    assert neg.sum() >= 50


def test_negative_radius_rule():
    lat = np.array([39.950, 39.951, 39.952, 39.953])
    lon = np.array([-75.190, -75.191, -75.192, -75.193])
    r = negative_radius(lat, lon, 25.0)
    assert 75.0 <= r <= 225.0
    assert negative_radius(lat * 0 + 39.95, lon * 0 - 75.19, 25.0) == pytest.approx(75.0)


def test_the_collection_sample_takes_whole_groups_up_to_the_cap():
    from app.engine.pipeline import Features
    from app.engine.training.svm_training import Geotagged, sample_references

    none = Features(local=None, xy=None, global_=None)
    # 30 groups of 1 to 4 references each (a photo and its crops), 75 references in all.
    refs, i = {}, 0
    for g in range(30):
        for _ in range(1 + g % 4):
            refs[i] = Geotagged(none, 39.95, -75.19, f"g{g}")
            i += 1
    assert len(sample_references(refs, 1000)) == len(refs)  # under the cap: every reference
    picked = sample_references(refs, 20, seed=3)
    assert 16 < len(picked) <= 20
    sizes = {g: sum(r.group == g for r in refs.values()) for g in {r.group for r in picked}}
    assert all(sum(p.group == g for p in picked) == n for g, n in sizes.items())  # whole groups only
    assert [p.group for p in picked] == [p.group for p in sample_references(refs, 20, seed=3)]  # seeded
    assert [p.group for p in picked] != [p.group for p in sample_references(refs, 20, seed=4)]


def test_definitions_saved_before_the_bank_field_still_match():
    """Pipeline.load compares a saved definition with the named one: a manifest written before
    ``svm_bank`` existed must still load (an existing data dir keeps its pipeline), and the new
    ``hybrid-nobank`` differs from ``hybrid`` in the bank alone."""
    from app.engine.configs import CONFIGS, PipelineConfig, get_config

    for name, config in CONFIGS.items():
        old = {k: v for k, v in config.model_dump().items() if k != "svm_bank"}
        assert (PipelineConfig(**old) == config) == config.svm_bank, name
    a, b = get_config("hybrid").model_dump(), get_config("hybrid-nobank").model_dump()
    assert {k for k in a if a[k] != b[k]} == {"name", "description", "svm_bank"}


def test_xfeat_descriptors_label_the_pattern_and_train_a_bank(models_dir, xfeat, tmp_path):
    """The bank is descriptor-agnostic: with XFeat (64-d learned) features the pasted pattern is labelled
    confusing, and a bank trained on those labels keeps the building's features over the pattern's."""
    from app.engine.registry import Kind, create

    extractor = create(Kind.LOCAL_EXTRACTOR, "xfeat", models_dir, max_keypoints=1500, long_side=640)
    f, labels, on_pattern, _ = _pattern_scene(extractor)
    assert f.descriptors.shape[1] == 64
    assert on_pattern.sum() > 30
    assert (labels[on_pattern] == -1).mean() > 0.7
    assert (labels[~on_pattern] == 1).mean() > 0.5
    assert (labels[~on_pattern] == -1).mean() < 0.1

    labelled = labels != 0
    bank = SvmBank.train(f.descriptors[labelled], labels[labelled], BankParams(n_clusters=2, hard_rounds=2, C=1.0))
    bank.save(tmp_path)
    again = SvmBank.load(tmp_path)
    d = again.decision(f.descriptors)
    assert np.median(d[~on_pattern]) > np.median(d[on_pattern])
