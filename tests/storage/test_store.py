"""The data directory: bulk rows with their codes, the change log, deduplication under races, deletion,
batched reads of any length, and storage failures that lose nothing."""

import resource
import sqlite3

import numpy as np
import pytest

from app.engine.configs import get_config
from app.engine.errors import IncompatibleArtifact
from app.engine.imageio import load_image
from app.engine.pipeline import Pipeline
from app.errors import StorageUnavailable
from app.manifests import read_manifest
from app.storage.errors import is_storage_error
from app.storage.store import NewReference, ReferenceStore

#: Every test here runs on SQLite and on PostgreSQL (the ``backend`` fixture).
pytestmark = pytest.mark.usefixtures("backend")


@pytest.fixture(scope="module")
def fitted(mini_manifest, squeezenet):
    rows = [r for r in read_manifest(mini_manifest) if r.split == "db"]
    pipe = Pipeline(get_config("hybrid-bin"), global_model=squeezenet)
    feats = [pipe.extract(load_image(r.image.read_bytes()).rgb) for r in rows]
    pipe.fit(feats)
    return pipe, rows, [pipe.encode_features(f) for f in feats]


def _database_errors() -> tuple[type[Exception], ...]:
    """Both engines' driver errors (psycopg where installed)."""
    try:
        import psycopg
    except ImportError:
        return (sqlite3.Error,)
    return (sqlite3.Error, psycopg.Error)


def _new(row, code=None) -> NewReference:
    return NewReference(
        row.image.read_bytes(),
        "jpeg",
        row.lat,
        row.lon,
        label=row.image.name,
        float_code=None if code is None else code.float_,
        binary_code=None if code is None else code.binary,
    )


def test_bulk_add_logs_index_changes_only(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path)
    store.bind(pipe)
    # Pending rows (an upload accepted, not encoded): rows change, the index version does not.
    items, job = store.add_many([_new(r) for r in rows[:4]], job=True)
    assert all(created for _, created in items) and store.version == 0 and store.count("pending") == 4
    assert store.job(job).status == "queued"
    ids = [i for i, _ in items]
    done = store.complete([(i, c.float_, c.binary, None) for i, c in zip(ids, codes, strict=False)])
    assert done == ids and store.version == 4 and store.job(job).status == "done"
    assert store.complete([(ids[0], codes[0].float_, codes[0].binary, None)]) == []  # idempotent
    assert store.version == 4
    # Pre-encoded rows (the bulk path of seeding) are indexed at once and logged in the same transaction.
    more, _ = store.add_many([_new(r, c) for r, c in zip(rows[4:8], codes[4:8], strict=True)])
    assert store.version == 8 and store.count() == 8
    # The same bytes again: the existing id, nothing written.
    again, _ = store.add_many([_new(rows[0])])
    assert again == [(ids[0], False)] and store.version == 8
    # Deleting an indexed row logs a delete; deleting a pending one changes no index.
    assert store.delete(ids[1]) and not store.delete(ids[1])
    assert [(c.op, c.ref_id) for c in store.changes_since(8)] == [("delete", ids[1])]
    assert store.get(ids[1]) is None and len(list(store.images_dir.iterdir())) == 7
    adds = store.changes_since(0)
    assert [c.op for c in adds[:8]] == ["add"] * 8
    assert adds[1].float_code is None  # deleted since: its add carries no codes
    assert np.frombuffer(adds[0].float_code, np.float32) == pytest.approx(codes[0].float_)
    refs, total = store.list(0, 10)
    assert total == 7 and [r.id for r in refs][0] == ids[0]


def test_a_duplicate_racing_in_from_another_process_returns_the_existing_id(tmp_path, fitted):
    """Two connections both pass the duplicate check before either inserts: the second gets the first's id."""
    pipe, rows, _ = fitted
    a, b = ReferenceStore(tmp_path), ReferenceStore(tmp_path)
    item_a, item_b = _new(rows[0]), _new(rows[0])
    assert a.existing_ids([item_a.sha256]) == {} and b.existing_ids([item_b.sha256]) == {}
    a.write_images([item_a])
    b.write_images([item_b])
    ((id_a, created_a),) = a.insert_rows([item_a])[0]
    ((id_b, created_b),) = b.insert_rows([item_b], job=True)[0]
    assert (id_b, created_b) == (id_a, False) and created_a
    assert a.count(None) == 1


def test_id_lists_of_any_length(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path)
    store.add_many([_new(r, c) for r, c in zip(rows[:3], codes[:3], strict=True)])
    ids = np.arange(1, 300_001)  # SQLite binds at most 250,000 variables: one JSON parameter instead
    lat, lon = store.positions(ids)
    assert np.isfinite(lat[:3]).all() and np.isnan(lat[3:]).all() and len(lat) == 300_000
    assert set(store.get_many(ids)) == {1, 2, 3}


def test_pages_by_id_read_the_same_rows_as_pages_by_offset(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path)
    store.add_many([_new(r, c) for r, c in zip(rows[:9], codes[:9], strict=True)])
    store.delete(4)
    by_offset = [r.id for r in store.list(0, 100)[0]]
    assert by_offset == [1, 2, 3, 5, 6, 7, 8, 9]
    forward, after = [], 0
    while after is not None:
        page = store.page(after=after, limit=3)
        forward.append([r.id for r in page.items])
        after = page.next_after
    assert forward == [[1, 2, 3], [5, 6, 7], [8, 9]]
    last = store.page(before=2**63 - 1, limit=3)
    assert [r.id for r in last.items] == [7, 8, 9] and last.next_after is None and last.prev_before == 7
    first = store.page(before=5, limit=3)
    assert [r.id for r in first.items] == [1, 2, 3] and first.prev_before is None and first.next_after == 3
    assert store.page(after=9).items == [] and store.count_in() == 8
    # A page emptied under a client (its rows deleted) still points at its neighbours, never at nothing.
    store.delete(8)
    store.delete(9)
    emptied = store.page(after=7, limit=3)
    assert emptied.items == [] and emptied.next_after is None and emptied.prev_before == 8
    assert [r.id for r in store.page(before=emptied.prev_before, limit=3).items] == [5, 6, 7]
    head = store.page(before=1, limit=3)
    assert head.items == [] and head.prev_before is None and head.next_after == 0
    assert [r.id for r in store.page(after=head.next_after, limit=3).items] == [1, 2, 3]
    assert store.page(after=2**63 - 1).prev_before == 2**63 - 1
    lats = sorted(r.lat for r in rows[:9])
    box = (-180.0, lats[0], 180.0, lats[3])  # 8 and 9 deleted: the box may hold fewer than 4 rows
    assert [r.id for r in store.page(after=0, limit=100, bbox=box).items] == [r.id for r in store.list(0, 100, box)[0]]
    assert store.count_in(box) == store.list(0, 1, box)[1]


def test_storage_failures_lose_nothing_and_recover(tmp_path, fitted):
    pipe, rows, _ = fitted
    store = ReferenceStore(tmp_path)
    ((first, _),) = store.add_many([_new(rows[0])])[0]
    # The images folder replaced by a plain file (what an operator's mistake or a broken mount looks like).
    store.images_dir.rename(tmp_path / "images.moved")
    store.images_dir.write_bytes(b"not a folder")
    with pytest.raises(StorageUnavailable):
        store.add_many([_new(rows[1])])
    store.images_dir.unlink()
    (tmp_path / "images.moved").rename(store.images_dir)
    assert store.count(None) == 1 and store.get(first) is not None
    # A full disk: writes beyond RLIMIT_FSIZE fail with EFBIG (Python ignores SIGXFSZ). The limit is below the
    # image's size: the WAL, checkpointed since the store was made, is too small to reach any fixed limit.
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (rows[2].image.stat().st_size // 2, hard))
    try:
        with pytest.raises(StorageUnavailable):
            store.add_many([_new(rows[2])])
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    # Recovered without reopening anything.
    ((second, created),) = store.add_many([_new(rows[2])])[0]
    assert created and store.count(None) == 2


def test_a_read_only_database_is_a_storage_error(tmp_path, fitted):
    pipe, rows, _ = fitted
    ReferenceStore(tmp_path).add_many([_new(rows[0])])
    ro = ReferenceStore(tmp_path, read_only=True)
    with pytest.raises(StorageUnavailable, match="cannot be written"):
        ro.insert_rows([_new(rows[1])])
    with pytest.raises(StorageUnavailable):
        ro.delete(1)
    assert ro.count(None) == 1
    with pytest.raises(_database_errors()) as bug:  # a bug (not storage) is not disguised as one
        ro.db.execute("SELECT nope FROM refs")
    assert not is_storage_error(bug.value)


def test_a_collection_refuses_codes_from_another_pipeline(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path)
    store.bind(pipe)
    store.add_many([_new(rows[0], codes[0])])
    other = Pipeline(get_config("hybrid-bin"), global_model=pipe.global_model)
    other.codebook, other.pca, other.binariser = pipe.codebook, pipe.pca, None
    with pytest.raises(IncompatibleArtifact, match="--config the collection was built with"):
        store.bind(other)
