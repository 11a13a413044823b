"""The live index: snapshot + change log, catch-up across processes, tombstones, integrity, replay."""

import json

import numpy as np
import pytest

from app.policies import SnapshotPolicy
from app.storage.snapshots import MANIFEST
from app.storage.store import NewReference, ReferenceStore
from app.usecases.collection import Collection
from tests.storage.test_store import fitted  # noqa: F401  (the module's fitted pipeline and codes)

#: Every test here runs on SQLite and on PostgreSQL (the ``backend`` fixture).
pytestmark = pytest.mark.usefixtures("backend")


def _fill(store, rows, codes, n, start=0):
    items = [
        NewReference(r.image.read_bytes(), "jpeg", r.lat, r.lon, float_code=c.float_, binary_code=c.binary)
        for r, c in zip(rows[start : start + n], codes[start : start + n], strict=True)
    ]
    return [i for i, _ in store.add_many(items)[0]]


def _top(col, code) -> int:
    s, i = col.search(code.float_, code.binary, 1, "float")
    return int(i[0])


def test_pending_uploads_change_nothing_and_completions_are_caught_up(tmp_path, fitted):  # noqa: F811
    pipe, rows, codes = fitted
    writer = Collection(ReferenceStore(tmp_path), pipe)
    reader = Collection(ReferenceStore(tmp_path), pipe)  # a second API process on the same data dir
    writer.write_snapshot()
    files_before = sorted(p.name for p in tmp_path.glob("*.faiss"))
    (items, _job) = writer.store.add_many(
        [NewReference(r.image.read_bytes(), "jpeg", r.lat, r.lon) for r in rows[:3]], job=True
    )
    ids = [i for i, _ in items]
    assert writer.store.version == 0 and reader.catch_up() == 0  # accepting touched no index
    writer.store.complete([(i, c.float_, c.binary, None) for i, c in zip(ids, codes, strict=False)])
    assert writer.catch_up() == 3 and reader.catch_up() == 3
    assert _top(reader, codes[1]) == ids[1] and reader.size == 3
    # A deletion by one process is gone from the other's searches at its next request.
    writer.store.delete(ids[1])
    assert _top(reader, codes[1]) != ids[1] and reader.size == 2 and reader.index.tombstones == 1
    assert sorted(p.name for p in tmp_path.glob("*.faiss")) == files_before  # no snapshot written
    assert writer.stats.full_rebuilds == 1 and reader.stats.full_rebuilds == 1  # the first load only


def test_snapshot_then_replay_after_restart(tmp_path, fitted):  # noqa: F811
    pipe, rows, codes = fitted
    col = Collection(ReferenceStore(tmp_path), pipe, SnapshotPolicy(every_changes=1000, every_seconds=3600))
    ids = _fill(col.store, rows, codes, 5)
    col.catch_up()
    col.store.delete(ids[0])
    col.catch_up()
    assert col.snapshot_due()  # loaded by a rebuild: the first snapshot is due at once
    assert col.write_snapshot() and col.index.tombstones == 0  # compacted on the way
    assert not col.snapshot_due() and not col.write_snapshot()
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert manifest["version"] == 6 and manifest["size"] == 4
    more = _fill(col.store, rows, codes, 2, start=5)
    col.store.delete(ids[2])
    restarted = Collection(ReferenceStore(tmp_path), pipe)
    assert restarted.stats.full_rebuilds == 0 and restarted.stats.replayed_at_start == 3
    assert restarted.size == 5 and restarted.version == 9
    assert _top(restarted, codes[6]) == more[1]
    assert not col.snapshot_due()  # 3 changes pending, policy 1000 / 1 h
    assert Collection(ReferenceStore(tmp_path), pipe, SnapshotPolicy(every_changes=3)).snapshot_due()


@pytest.mark.parametrize("damage", ["corrupt-middle", "truncate-file", "truncate-manifest", "delete-file"])
def test_a_damaged_snapshot_is_never_served(tmp_path, fitted, damage):  # noqa: F811
    pipe, rows, codes = fitted
    col = Collection(ReferenceStore(tmp_path), pipe)
    ids = _fill(col.store, rows, codes, 6)
    col.catch_up()
    col.write_snapshot()
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    path = tmp_path / manifest["files"]["float"]["file"]
    data = bytearray(path.read_bytes())
    if damage == "corrupt-middle":  # same size, garbage in the vectors: loads fine without a checksum
        mid = len(data) // 2
        data[mid : mid + 4096] = np.random.default_rng(0).integers(0, 255, 4096, dtype=np.uint8).tobytes()
        path.write_bytes(bytes(data))
    elif damage == "truncate-file":
        path.write_bytes(bytes(data[: len(data) // 3]))
    elif damage == "truncate-manifest":
        text = (tmp_path / MANIFEST).read_text()
        (tmp_path / MANIFEST).write_text(text[: len(text) // 2])
    else:
        path.unlink()
    again = Collection(ReferenceStore(tmp_path), pipe)
    assert again.stats.full_rebuilds == 1 and again.size == 6
    assert all(_top(again, c) == i for i, c in zip(ids, codes, strict=False))
    assert again.write_snapshot()  # and the writer replaces it
    assert Collection(ReferenceStore(tmp_path), pipe).stats.full_rebuilds == 0


@pytest.mark.parametrize("compaction", [False, True], ids=["in place", "compacted copy"])
def test_snapshot_write_keeps_changes_that_arrive_meanwhile(tmp_path, fitted, compaction):  # noqa: F811
    """Without a compaction due the snapshot is written from the served index itself (no copy); with one
    (a tombstone of the flat index) from a compacted copy swapped in after a replay. Either way, changes
    that another process logs while the file is being finished (without the lock) are kept."""
    pipe, rows, codes = fitted
    col = Collection(ReferenceStore(tmp_path), pipe)
    ids = _fill(col.store, rows, codes, 3)
    col.catch_up()
    if compaction:
        col.store.delete(ids[0])
    else:
        assert col.write_snapshot()  # the rebuild's snapshot
    ids += _fill(col.store, rows, codes, 1, start=3)
    col.catch_up()
    assert col.index.compaction_due is compaction
    served, v0, size0 = col.index, col.version, col.size
    # Another process adds while the file is written: the binding is read after the files, without the lock.
    original = col.store.binding
    added = []

    def later(version):
        if not added:
            added.extend(_fill(col.store, rows, codes, 2, start=4))
            col.catch_up()
        return original(version)

    col.store.binding = later
    assert col.write_snapshot()
    col.store.binding = original
    assert added and json.loads((tmp_path / MANIFEST).read_text())["version"] == v0
    assert col.size == size0 + 2 and col.version == v0 + 2
    assert (col.index is served) is not compaction  # in place: the same index object keeps serving
    assert col.index.tombstones == 0
    for i, ref_id in zip(range(1, 6), ids[1:] + added, strict=True):
        assert _top(col, codes[i]) == ref_id
    restarted = Collection(ReferenceStore(tmp_path), pipe)
    assert restarted.stats.full_rebuilds == 0 and restarted.stats.replayed_at_start == 2
    assert restarted.size == col.size


def test_the_time_rule_counts_from_the_first_change_not_in_a_snapshot(tmp_path, fitted):  # noqa: F811
    import time

    pipe, rows, codes = fitted
    col = Collection(ReferenceStore(tmp_path), pipe, SnapshotPolicy(every_changes=1000, every_seconds=0.5))
    col.write_snapshot()
    time.sleep(0.6)  # an old snapshot alone makes nothing due
    assert not col.snapshot_due()
    _fill(col.store, rows, codes, 1)
    col.catch_up()
    assert not col.snapshot_due()  # one change, just now
    time.sleep(0.6)
    assert col.snapshot_due() and col.write_snapshot() and not col.snapshot_due()
