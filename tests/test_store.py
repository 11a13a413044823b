"""The data directory: durable rows with their codes, deduplication, deletion, index snapshots."""

import json

import numpy as np
import pytest

from app.datasets import read_manifest
from app.engine.configs import get_config
from app.engine.errors import IncompatibleArtifact
from app.engine.pipeline import Pipeline
from app.store import ReferenceStore


@pytest.fixture(scope="module")
def fitted(mini_manifest, squeezenet):
    rows = [r for r in read_manifest(mini_manifest) if r.split == "db"]
    pipe = Pipeline(get_config("hybrid-bin"), cnn=squeezenet)
    from app.engine.imageio import load_image

    feats = [pipe.extract(load_image(r.image.read_bytes()).rgb) for r in rows]
    pipe.fit(feats)
    return pipe, rows, [pipe.encode_features(f) for f in feats]


def _fill(store, pipe, rows, codes, n):
    ids = []
    for r, c in zip(rows[:n], codes[:n], strict=True):
        ref_id, created = store.add(r.image.read_bytes(), "jpeg", r.lat, r.lon, c.float_, c.binary, label=r.image.name)
        assert created
        ids.append(ref_id)
    return ids


def test_add_dedup_delete_and_snapshot(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path)
    store.bind(pipe)
    ids = _fill(store, pipe, rows, codes, 5)
    again, created = store.add(rows[0].image.read_bytes(), "jpeg", 0, 0, codes[0].float_, codes[0].binary)
    assert (again, created) == (ids[0], False)
    index = store.build_index(pipe)
    assert index.size == 5 == store.count()
    assert json.loads((tmp_path / "index.json").read_text())["version"] == store.version
    assert (tmp_path / f"float-v{store.version}.faiss").exists()

    assert store.delete(ids[1]) and not store.delete(ids[1])
    assert not store.image_path(ids[1]) and store.get(ids[1]) is None
    assert len(list((tmp_path / "images").iterdir())) == 4
    refs, total = store.list(0, 10)
    assert total == 4 and [r.id for r in refs] == [ids[0], *ids[2:]]
    lat, lon = rows[0].lat, rows[0].lon
    assert ids[0] in store.ids_in_bbox((lon - 1e-4, lat - 1e-4, lon + 1e-4, lat + 1e-4))
    store.close()


def test_stale_or_missing_snapshot_is_rebuilt_from_codes(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path)
    store.bind(pipe)
    _fill(store, pipe, rows, codes, 4)
    index = store.build_index(pipe)
    # A reference committed after the last snapshot (a crash before the snapshot was written).
    store.add(rows[4].image.read_bytes(), "jpeg", rows[4].lat, rows[4].lon, codes[4].float_, codes[4].binary)
    reopened = ReferenceStore(tmp_path)
    rebuilt = reopened.build_index(pipe)
    assert rebuilt.size == 5 and index.size == 4
    s, i = rebuilt.search(codes[4].float_, codes[4].binary, 1, "two-stage")
    assert reopened.get(int(i[0])).lat == rows[4].lat
    (tmp_path / "index.json").unlink()
    assert ReferenceStore(tmp_path).build_index(pipe).size == 5


def test_a_collection_refuses_codes_from_another_pipeline(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path)
    store.bind(pipe)
    _fill(store, pipe, rows, codes, 1)
    other = Pipeline(get_config("hybrid-bin"), cnn=pipe.cnn)
    other.codebook, other.pca, other.binariser = pipe.codebook, pipe.pca, None
    with pytest.raises(IncompatibleArtifact, match="--config the collection was built with"):
        store.bind(other)
    assert np.isfinite(store.positions(np.array([1]))[0]).all()
