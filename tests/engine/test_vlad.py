"""Codebooks and VLAD: the aggregation's normalisations and the codebook's persistence."""

import numpy as np
import pytest

from app.engine.errors import IncompatibleArtifact, ModelNotReady
from app.engine.vlad import Codebook, vlad


@pytest.fixture(scope="module")
def blobs():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(4, 8)) * 5
    x = np.vstack([c + rng.normal(size=(200, 8)) for c in centres]).astype(np.float32)
    return centres, x


@pytest.mark.parametrize("algorithm", ["minibatch", "kmeans"])
def test_codebook_finds_separated_clusters(blobs, algorithm):
    centres, x = blobs
    cb = Codebook.fit(x, 4, algorithm, seed=0)
    for c in centres:
        assert np.min(np.linalg.norm(cb.centers - c, axis=1)) < 0.5


def test_vlad_normalisations(blobs):
    _, x = blobs
    cb = Codebook.fit(x, 4, seed=0)
    v = vlad(x[:50], cb, alpha=0.5, intra_norm=True)
    assert v.shape == (4 * 8,)
    assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-5)
    blocks = v.reshape(4, 8)
    nonzero = np.linalg.norm(blocks, axis=1) > 0
    # intra-normalised blocks all have the same length before the final L2
    assert np.allclose(np.linalg.norm(blocks[nonzero], axis=1), 1 / np.sqrt(nonzero.sum()), atol=1e-5)


def test_vlad_of_the_centres_is_zero_and_empty_input_is_zero(blobs):
    _, x = blobs
    cb = Codebook.fit(x, 4, seed=0)
    assert not vlad(cb.centers, cb).any()
    assert not vlad(np.zeros((0, 8), np.float32), cb).any()


def test_vlad_residual_sums_without_normalisation(blobs):
    _, x = blobs
    cb = Codebook.fit(x, 4, seed=0)
    sample = x[:30]
    a = cb.assign(sample)
    expected = np.zeros((4, 8))
    for d, k in zip(sample, a, strict=True):
        expected[k] += d - cb.centers[k]
    expected = expected.ravel() / np.linalg.norm(expected)
    assert np.allclose(vlad(sample, cb, alpha=1.0, intra_norm=False), expected, atol=1e-5)


def test_codebook_round_trip_and_refusals(blobs, tmp_path):
    _, x = blobs
    cb = Codebook.fit(x, 4, seed=0)
    cb.save(tmp_path)
    again = Codebook.load(tmp_path)
    assert np.array_equal(again.centers, cb.centers) and again.manifest["data_hash"] == cb.manifest["data_hash"]
    with pytest.raises(ModelNotReady):
        Codebook.load(tmp_path / "nowhere")
    (tmp_path / "codebook.json").write_text('{"kind": "codebook", "format_version": 99}')
    with pytest.raises(IncompatibleArtifact):
        Codebook.load(tmp_path)
