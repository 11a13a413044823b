"""FAISS indexes: every kind adds, finds, removes (or tombstones), persists and rebuilds."""

import numpy as np
import pytest

from app.engine.index.vectors import VectorIndex


def _data(binary: bool, n: int = 300, dim: int = 64):
    rng = np.random.default_rng(0)
    if binary:
        return rng.integers(0, 256, (n, dim // 8), dtype=np.uint8)
    x = rng.standard_normal((n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


KINDS = [(b, k) for b in (False, True) for k in ("flat", "ivf", "hnsw")]


@pytest.mark.parametrize("binary, kind", KINDS)
def test_add_search_remove_persist(binary, kind):
    x = _data(binary)
    ids = np.arange(1000, 1300)
    idx = VectorIndex(64, binary, kind)
    idx.add(ids, x)
    assert idx.ntotal == 300
    scores, found = idx.search(x[:5], 3)
    assert (found[:, 0] == ids[:5]).all()
    assert np.allclose(scores[:, 0], 1.0) and (scores <= 1).all() and (scores >= 0).all()
    assert (np.diff(scores, axis=1) <= 1e-6).all()  # best first

    assert idx.remove([1000, 1001, 424242]) == 2
    assert idx.ntotal == 298
    _, found = idx.search(x[:2], 5)
    assert not np.isin(found, [1000, 1001]).any()
    assert np.array_equal(idx.reconstruct([1005])[0], x[5])

    again = VectorIndex(64, binary, kind)
    again.load_bytes(idx.to_bytes(), idx.tombstones)
    assert again.ntotal == 298
    assert np.array_equal(again.search(x[:3], 4)[1], idx.search(x[:3], 4)[1])

    rebuilt = VectorIndex.rebuild(idx, idx.ids(), idx.reconstruct(idx.ids()))
    assert rebuilt.ntotal == 298 and not rebuilt.tombstones
    assert rebuilt.search(x[5:6], 1)[1][0, 0] == 1005


@pytest.mark.parametrize("binary", [False, True])
def test_region_restricts_the_search_itself(binary):
    x = _data(binary)
    idx = VectorIndex(64, binary, "flat")
    idx.add(np.arange(300), x)
    allowed = np.array([7, 8, 9, 250])
    scores, found = idx.search(x[7:8], 10, allowed=allowed)
    assert found[0, 0] == 7
    assert set(found[0][found[0] >= 0]) == set(allowed.tolist())
    assert (found[0][4:] == -1).all()


def test_hnsw_deletions_are_tombstones_until_rebuild():
    x = _data(False)
    idx = VectorIndex(64, False, "hnsw")
    idx.add(np.arange(300), x)
    idx.remove(list(range(100)))
    assert idx.needs_rebuild and len(idx.tombstones) == 100
    idx.add(np.array([5]), x[5:6] * 1.0)  # re-adding an id revives it
    assert 5 not in idx.tombstones


def test_wrong_dimensions_are_refused():
    idx = VectorIndex(64, False, "flat")
    with pytest.raises(ValueError, match="dimension"):
        idx.add(np.arange(2), np.zeros((2, 32), np.float32))


def test_empty_index_returns_nothing():
    idx = VectorIndex(64, True, "flat")
    scores, found = idx.search(np.zeros((1, 8), np.uint8), 5)
    assert (found == -1).all()
