"""PCA-whitening and binary codes."""

import numpy as np
import pytest

from app.engine.codes import Binariser
from app.engine.pca import PcaWhitening


@pytest.fixture(scope="module")
def vectors():
    rng = np.random.default_rng(1)
    basis = rng.normal(size=(40, 300))
    x = rng.normal(size=(400, 40)) * np.linspace(5, 0.5, 40) @ basis
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def test_whitening_equalises_variance(vectors, tmp_path):
    pca = PcaWhitening.fit(vectors, 16, power=0.5)
    y = (vectors - pca.mean) @ pca._projection
    assert np.allclose(y.var(axis=0), 1.0, rtol=0.05)
    out = pca.transform(vectors)
    assert out.shape == (400, 16)
    assert np.allclose(np.linalg.norm(out, axis=1), 1, atol=1e-5)
    pca.save(tmp_path)
    assert np.allclose(PcaWhitening.load(tmp_path).transform(vectors), out)


def test_dimension_is_capped_by_the_training_set(vectors):
    assert PcaWhitening.fit(vectors[:10], 64).dim == 9


@pytest.mark.parametrize("method", ["sign", "itq"])
def test_codes_keep_neighbours_close(vectors, method, tmp_path):
    pca = PcaWhitening.fit(vectors, 32, power=0.5)
    z = pca.transform(vectors)
    b = Binariser.fit(z, 32, method)
    codes = b.encode(z)
    assert codes.shape == (400, 4) and codes.dtype == np.uint8
    bits = np.unpackbits(codes, axis=1)
    assert 0.35 < bits.mean() < 0.65  # median thresholds: every bit splits the set
    noisy = pca.transform(vectors + np.random.default_rng(2).normal(scale=0.01, size=vectors.shape))
    near = (np.unpackbits(b.encode(noisy), axis=1) != bits).sum(1).mean()
    far = (bits[:200] != bits[200:]).sum(1).mean()
    assert near < far / 3
    b.save(tmp_path)
    assert np.array_equal(Binariser.load(tmp_path).encode(z), codes)


def test_itq_quantises_better_than_plain_signs(vectors):
    z = PcaWhitening.fit(vectors, 32, power=0.0).transform(vectors)

    def quantisation_error(b: Binariser) -> float:
        proj = z @ b.rotation
        proj /= np.linalg.norm(proj, axis=1, keepdims=True)
        signs = np.where(proj > 0, 1.0, -1.0) / np.sqrt(proj.shape[1])
        return float(((signs - proj) ** 2).sum(1).mean())

    assert quantisation_error(Binariser.fit(z, 32, "itq")) < quantisation_error(Binariser.fit(z, 32, "sign"))
