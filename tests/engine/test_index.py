"""Index kinds: every registered kind adds, finds, removes (or tombstones), persists and compacts through the
``VectorIndex`` protocol; kinds that need training refuse vectors until the explicit training step."""

import numpy as np
import pytest

from app.engine.configs import get_config
from app.engine.index.base import IndexNotTrained, UnknownIndexKind, VectorIndex, build_index, index_kinds
from app.engine.index.references import ReferenceIndex


def _data(binary: bool, n: int = 300, dim: int = 64):
    rng = np.random.default_rng(0)
    if binary:
        return rng.integers(0, 256, (n, dim // 8), dtype=np.uint8)
    x = rng.standard_normal((n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


KINDS = [(b, k) for b in (False, True) for k in ("flat", "ivf", "hnsw")]


def _built(kind: str, binary: bool, x: np.ndarray) -> VectorIndex:
    idx = build_index(kind, 64, binary)
    idx.train(x)
    return idx


@pytest.mark.parametrize("binary, kind", KINDS)
def test_add_search_remove_persist(binary, kind, tmp_path):
    x = _data(binary)
    ids = np.arange(1000, 1300)
    idx = _built(kind, binary, x)
    assert isinstance(idx, VectorIndex) and idx.kind == kind and idx.is_trained
    idx.add(ids, x)
    assert idx.size == 300
    scores, found = idx.search(x[:5], 3)
    assert (found[:, 0] == ids[:5]).all()
    assert np.allclose(scores[:, 0], 1.0) and (scores <= 1).all() and (scores >= 0).all()
    assert (np.diff(scores, axis=1) <= 1e-6).all()  # best first

    assert idx.remove([1000, 1001, 424242]) == 2
    assert idx.size == 298 and idx.removed_ids().tolist() == [1000, 1001]
    _, found = idx.search(x[:2], 5)
    assert not np.isin(found, [1000, 1001]).any()
    assert idx.score_ids(x[5], np.array([1005]))[0] == pytest.approx(1.0)

    idx.dump(tmp_path / "part.faiss")
    again = build_index(kind, 64, binary)
    again.load(tmp_path / "part.faiss")
    again.remove(idx.removed_ids())
    assert again.size == 298
    assert np.array_equal(again.search(x[:3], 4)[1], idx.search(x[:3], 4)[1])

    twin = idx.copy()
    idx.remove(list(range(1002, 1100)))  # past 20 %: every kind drops them at compaction
    assert twin.size == 298  # a copy is independent
    idx.compact()
    assert idx.size == 200 and len(idx.removed_ids()) == 0 and len(idx.ids()) == 200
    assert idx.search(x[150:151], 1)[1][0, 0] == 1150
    assert twin.size == 298 and twin.search(x[50:51], 1)[1][0, 0] == 1050  # the copy kept its own vectors
    assert idx.stats()["kind"] == kind and idx.stats()["size"] == 200


@pytest.mark.parametrize("binary", [False, True])
def test_ivf_is_trained_explicitly_and_refuses_vectors_before(binary):
    x = _data(binary, n=2000)
    idx = build_index("ivf", 64, binary)
    assert not idx.is_trained
    with pytest.raises(IndexNotTrained, match="needs training"):
        idx.add(np.arange(3), x[:3])
    idx.train(x)
    idx.add(np.arange(5), x[:5])  # a small first batch no longer decides the lists
    stats = idx.stats()
    assert stats["nlist"] == int(np.sqrt(2000)) and stats["nprobe"] == stats["nlist"] // 4


def test_flat_and_hnsw_need_no_training():
    assert build_index("flat", 64, False).is_trained and build_index("hnsw", 64, True).is_trained


@pytest.mark.parametrize("binary", [False, True])
def test_region_restricts_the_search_itself(binary):
    x = _data(binary)
    idx = build_index("flat", 64, binary)
    idx.add(np.arange(300), x)
    allowed = np.array([7, 8, 9, 250])
    scores, found = idx.search(x[7:8], 10, allowed=allowed)
    assert found[0, 0] == 7
    assert set(found[0][found[0] >= 0]) == set(allowed.tolist())
    assert (found[0][4:] == -1).all()


def test_hnsw_deletions_are_tombstones_until_compaction():
    x = _data(False)
    idx = build_index("hnsw", 64, False)
    idx.add(np.arange(300), x)
    idx.remove(list(range(50)))
    idx.compact()  # under 20 % dead: a graph keeps its tombstones
    assert len(idx.removed_ids()) == 50
    idx.add(np.array([5]), x[5:6] * 1.0)  # re-adding an id revives it
    assert 5 not in idx.removed_ids()


def test_wrong_dimensions_are_refused():
    idx = build_index("flat", 64, False)
    with pytest.raises(ValueError, match="dimension"):
        idx.add(np.arange(2), np.zeros((2, 32), np.float32))


def test_empty_index_returns_nothing():
    idx = build_index("flat", 64, True)
    scores, found = idx.search(np.zeros((1, 8), np.uint8), 5)
    assert (found == -1).all()


def test_an_unknown_kind_is_named_with_the_choices():
    assert {"flat", "ivf", "hnsw"} <= set(index_kinds())
    with pytest.raises(UnknownIndexKind, match="unknown index kind 'nope'; choose one of .*flat.*hnsw.*ivf"):
        build_index("nope", 64, False)


def test_a_reference_index_trains_saves_and_loads_its_trained_parts(tmp_path):
    config = get_config("hybrid-bin").model_copy(update={"float_index": "ivf", "binary_index": "hnsw"})
    xf, xb = _data(False, n=400), _data(True, n=400)
    index = ReferenceIndex(config, 64, 64)
    assert not index.is_trained
    index.train(xf, xb)
    assert index.save_trained(tmp_path) == ["index-float.faiss"]  # hnsw needs no training: nothing saved
    loaded = ReferenceIndex(config, 64, 64)
    loaded.load_trained(tmp_path)
    assert loaded.is_trained
    assert loaded.stats()["float"]["nlist"] == index.stats()["float"]["nlist"] == 10
    loaded.add(np.arange(400), xf, xb)
    scores, ids = loaded.search(xf[3], xb[3], 1)
    assert ids[0] == 3


def test_search_threads_come_from_settings_not_from_the_environment_at_import():
    """FAISS's thread count is process state: checked in a fresh interpreter."""
    import os
    import subprocess
    import sys

    code = (
        "import faiss\n"
        "import app.engine.index.faiss_index as fi\n"
        "from app.settings import Settings\n"
        "assert faiss.omp_get_max_threads() == 1, 'read at import'\n"
        "fi.set_search_threads(Settings().faiss_threads)\n"
        "print(faiss.omp_get_max_threads())\n"
    )
    env = {**os.environ, "GEOLOC_FAISS_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "2"


@pytest.mark.parametrize("binary", [False, True])
def test_flat_sample_is_live_codes_drawn_reproducibly(binary):
    """The compressed kind's training sample (``FlatIndex.sample``): live codes only, the same draw each time,
    at most ``n``; and a reference index of the compressed kinds trained on it finds its own codes."""
    x = _data(binary)
    idx = build_index("flat", 64, binary)
    ids = np.arange(len(x)) + 1000
    idx.add(ids, x)
    idx.remove(ids[:50])
    everything = idx.sample(10_000)
    assert len(everything) == len(x) - 50 and (everything == x[50:]).all()
    some = idx.sample(100)
    assert len(some) == 100 and (some == idx.sample(100)).all()
    assert {r.tobytes() for r in some} <= {r.tobytes() for r in x[50:]}
    assert len(build_index("flat", 64, binary).sample(5)) == 0


def test_compressed_twin_is_trained_on_the_sample_and_serves():
    index = ReferenceIndex(get_config("hybrid-bin"), 64, 64)
    f, b = _data(False), _data(True)
    ids = np.arange(len(f))
    index.add(ids, f, b)
    assert index.switches_by_size and index.is_exact
    twin = index.compressed(index.size, *index.sample(ReferenceIndex.sample_size(index.size)))
    assert twin.kinds() == {"float": "ivf-rabitq", "binary": "binary-ivf"} and twin.size == 0
    twin.add(ids, f, b)
    for mode in ("float", "binary", "two-stage"):
        assert twin.search(f[7], b[7], 1, mode)[1][0] == 7, mode
