"""The store's side of a re-fit: next codes per target, the switch transaction, the copy after it, and the
fingerprint guard on completion (SQLite only: codes are plain arrays here, the pipelines are tested in
tests/api/test_refit.py)."""

from dataclasses import replace

import numpy as np
import pytest

from app.errors import StaleReindex
from app.storage.generations import ReindexTarget
from app.storage.store import NewReference, ReferenceStore

#: Every test here runs on SQLite and on PostgreSQL (the ``backend`` fixture).
pytestmark = pytest.mark.usefixtures("backend")

TARGET = ReindexTarget(generation=1, pipeline="pipelines/x-g1", config="x", fingerprint="x:new")


def _store(tmp_path, n=4):
    store = ReferenceStore(tmp_path)
    store.set_meta("fingerprint", "x:old")
    items = [NewReference(bytes([i]) * 10, "jpg", 1.0, 2.0, float_code=np.full(4, i, np.float32)) for i in range(n)]
    ids = [i for i, _ in store.add_many(items)[0]]
    return store, ids


def _codes(store) -> dict[int, float]:
    _, ids, f, _ = store.all_codes()
    return {int(i): float(c[0]) for i, c in zip(ids, f, strict=True)}


def test_switch_needs_every_code_then_readers_see_the_new_ones_before_and_after_the_copy(tmp_path):
    store, ids = _store(tmp_path)
    assert store.start_reindex(TARGET) == 0
    store.put_next_codes(TARGET, [(i, np.full(4, 100 + i, np.float32), None, None) for i in ids[:3]])
    assert store.reindex_missing() == 1 and [i for i, _ in store.reindex_todo(10)] == [ids[3]]
    assert store.switch_generation(TARGET) is None  # one reference has no new code yet
    assert store.start_reindex(TARGET) == 3  # the same target again continues
    store.put_next_codes(TARGET, [(ids[3], None, None, "cannot decode")])
    old = _codes(store)
    assert store.switch_generation(TARGET) == 1
    assert store.head()[1] == 1 and store.get_meta("fingerprint") == "x:new"
    assert store.get_meta("pipeline") == "pipelines/x-g1" and store.reindex_target() is None
    assert store.get(ids[3]).status == "failed" and "cannot decode" in store.get(ids[3]).error
    new = {i: 100.0 + i for i in ids[:3]}
    assert _codes(store) == new != {i: old[i] for i in ids[:3]}  # read through the renamed table
    assert [c.float_code for c in store.changes_since(0) if c.ref_id == ids[0]][0] == np.full(
        4, 100 + ids[0], np.float32
    ).tobytes()
    assert store.migrate_switched(batch=2) == 2 and store.migrate_switched(batch=2) == 2  # the failed row too
    assert store.migrate_switched() == 0 and _codes(store) == new  # copied into refs: the same codes
    row = store.db.execute("SELECT float_code FROM refs WHERE id=?", (ids[0],)).fetchone()[0]
    assert np.frombuffer(row, np.float32)[0] == 100 + ids[0]


def test_another_target_starts_over_and_the_old_one_is_refused(tmp_path):
    store, ids = _store(tmp_path, 2)
    store.start_reindex(TARGET)
    store.put_next_codes(TARGET, [(ids[0], np.zeros(4, np.float32), None, None)])
    other = replace(TARGET, fingerprint="x:other")
    assert store.start_reindex(other) == 0  # a different target: the codes so far are dropped
    with pytest.raises(StaleReindex):
        store.put_next_codes(TARGET, [(ids[1], np.zeros(4, np.float32), None, None)])
    with pytest.raises(StaleReindex):
        store.switch_generation(TARGET)
    store.abandon_reindex()
    assert store.reindex_target() is None and store.head()[1] == 0


def test_completion_by_another_pipeline_than_the_data_dirs_records_nothing(tmp_path):
    store, _ = _store(tmp_path, 1)
    ((pending, _),), _ = store.add_many([NewReference(b"pending", "jpg", 1.0, 2.0)])
    code = np.ones(4, np.float32)
    assert store.complete([(pending, code, None, None)], fingerprint="x:stale") == []
    assert store.get(pending).status == "pending"
    assert store.complete([(pending, code, None, None)], fingerprint="x:old") == [pending]


def test_the_code_stream_hands_out_chunks_of_one_consistent_read(tmp_path):
    """A cold start reads every code chunk by chunk on a connection of its own: the chunks hold each indexed
    reference once, in id order, as arrays; a change committed while the stream is open is not in it (it is
    after the version the stream reports, so the catch-up applies it)."""
    store, ids = _store(tmp_path, n=7)
    with store.code_stream(chunk=3) as stream:
        version = stream.version
        first = next(stream.chunks)
        store.add_many([NewReference(b"late" * 3, "jpg", 1.0, 2.0, float_code=np.full(4, 99, np.float32))])
        chunks = [first, *stream.chunks]
    assert [len(c.ids) for c in chunks] == [3, 3, 1]
    assert np.concatenate([c.ids for c in chunks]).tolist() == ids
    assert all(c.float_codes.dtype == np.float32 and c.float_codes.shape == (len(c.ids), 4) for c in chunks)
    assert [float(c.float_codes[i, 0]) for c in chunks for i in range(len(c.ids))] == list(range(7))
    assert all(c.binary_codes is None for c in chunks)  # this configuration stores no binary codes
    assert stream.generation == 0 and version == store.version - 1
    assert len(store.all_codes()[1]) == 8
