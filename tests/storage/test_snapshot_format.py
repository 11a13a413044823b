"""Snapshots written before the index seam still load: format 2 is the FAISS files of ``IndexIDMap2`` the
service wrote then (``faiss.serialize_index``), with the tombstones in the manifest. The old writer is
re-created here from what it did, so that a data dir made by an older version is known to start from its
snapshot (no rebuild), tombstones included."""

import hashlib
import time

import faiss
import numpy as np
import pytest

from app.engine.configs import PipelineConfig
from app.engine.imageio import load_image
from app.engine.pipeline import Pipeline
from app.manifests import read_manifest
from app.storage.snapshots import FORMAT, MANIFEST, SnapshotFile, SnapshotManifest
from app.storage.store import NewReference, ReferenceStore
from app.usecases.collection import Collection

#: Float and binary codes (both parts of a snapshot), quick to fit: GeM codes, no local features.
CONFIG = PipelineConfig(
    name="gem-bin",
    description="SqueezeNet GeM, floats and sign bits (test)",
    local=None,
    codebook=None,
    cnn_global_weight=1.0,
    cnn_short_side=224,
    pca_dim=16,
    binary="sign",
    bits=16,
)


@pytest.fixture(scope="module")
def fitted(mini_manifest, squeezenet):
    rows = [r for r in read_manifest(mini_manifest) if r.split == "db"]
    pipe = Pipeline(CONFIG, global_model=squeezenet)
    feats = [pipe.extract(load_image(r.image.read_bytes()).rgb) for r in rows]
    pipe.fit(feats)
    return pipe, rows, [pipe.encode_features(f) for f in feats]


def _old_part(codes: np.ndarray, ids: np.ndarray, binary: bool) -> bytes:
    """What the former ``VectorIndex.to_bytes`` gave for a flat index."""
    if binary:
        index = faiss.IndexBinaryIDMap2(faiss.IndexBinaryFlat(codes.shape[1] * 8))
        index.add_with_ids(codes, ids)
        return faiss.serialize_index_binary(index).tobytes()
    index = faiss.IndexIDMap2(faiss.IndexFlatIP(codes.shape[1]))
    index.add_with_ids(codes, ids)
    return faiss.serialize_index(index).tobytes()


def _write_old_snapshot(store: ReferenceStore, pipe, ids, fcodes, bcodes, dead: int) -> None:
    """The former ``write_snapshot``: one file per part, the deleted id as a tombstone in the manifest."""
    version = store.version
    files = {}
    for part, codes, binary in (("float", fcodes, False), ("binary", bcodes, True)):
        data = _old_part(codes, ids, binary)
        name = f"{part}-g0-v{version}.faiss"
        (store.snapshots_dir / name).write_bytes(data)
        files[part] = SnapshotFile(name, len(data), hashlib.sha256(data).hexdigest(), [dead])
    binding = store.binding(version)
    manifest = SnapshotManifest(
        format=2,
        version=version,
        generation=0,
        size=len(ids) - 1,
        config=pipe.config.name,
        fingerprint=pipe.fingerprint,
        float_dim=pipe.float_dim,
        bits=pipe.bits,
        files=files,
        written_at=time.time(),
        database_id=binding.database_id,
        ref_high_water=binding.ref_high_water,
        last_change=binding.last_change,
    )
    (store.snapshots_dir / MANIFEST).write_text(manifest.to_json())


def test_a_snapshot_written_before_the_index_seam_loads(tmp_path, fitted):
    pipe, rows, codes = fitted
    assert FORMAT == 2
    store = ReferenceStore(tmp_path)
    items = [
        NewReference(r.image.read_bytes(), "jpeg", r.lat, r.lon, float_code=c.float_, binary_code=c.binary)
        for r, c in zip(rows[:5], codes[:5], strict=True)
    ]
    ids = np.array([i for i, _ in store.add_many(items)[0]], np.int64)
    fcodes = np.stack([c.float_ for c in codes[:5]])
    bcodes = np.stack([c.binary for c in codes[:5]])
    store.delete(int(ids[1]))
    _write_old_snapshot(store, pipe, ids, fcodes, bcodes, dead=int(ids[1]))
    store.close()

    col = Collection(ReferenceStore(tmp_path), pipe)
    assert col.stats.full_rebuilds == 0 and col.stats.replayed_at_start == 0  # served from the old files
    assert col.size == 4 and col.index.tombstones == 1
    assert sorted(col.index.ids().tolist()) == sorted(np.delete(ids, 1).tolist())
    _, found = col.search(codes[3].float_, codes[3].binary, 2, "two-stage")
    assert found[0] == ids[3] and ids[1] not in found
    _, found = col.search(codes[1].float_, codes[1].binary, 5, "binary")
    assert ids[1] not in found

    # What the new code writes is the same kind of FAISS file: the old reader reads it.
    r, c = rows[5], codes[5]
    col.store.add_many(
        [NewReference(r.image.read_bytes(), "jpeg", r.lat, r.lon, float_code=c.float_, binary_code=c.binary)]
    )
    assert col.write_snapshot()
    float_file = next(tmp_path.glob("float-g0-v*.faiss"))
    old_reader = faiss.deserialize_index(np.fromfile(float_file, np.uint8))
    assert isinstance(old_reader, faiss.IndexIDMap2) and old_reader.ntotal == 5  # compacted: the dead one is gone
    col.store.close()
