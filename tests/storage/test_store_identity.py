"""The database's identity and the snapshots bound to it; checkpoints; the modes of what the store creates.

A snapshot is only served for the database (and the state of it) it was made from: one ahead of the
database (a copy without its -wal), one of another database, or one whose change log diverged is rebuilt
from SQLite, and the reference ids it knew are never handed out again."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import stat

import pytest

from app.engine.configs import get_config
from app.engine.imageio import load_image
from app.engine.pipeline import Pipeline
from app.manifests import read_manifest
from app.storage.database import DB_NAME
from app.storage.snapshots import MANIFEST, SnapshotMismatch, SnapshotUnverifiable, check_binding
from app.storage.snapshots import read_manifest as read_manifest_of
from app.storage.store import NewReference, ReferenceStore
from app.usecases.collection import Collection


@pytest.fixture(scope="module")
def fitted(mini_manifest, squeezenet):
    rows = [r for r in read_manifest(mini_manifest) if r.split == "db"][:12]
    pipe = Pipeline(get_config("hybrid-bin"), global_model=squeezenet)
    feats = [pipe.extract(load_image(r.image.read_bytes()).rgb) for r in rows]
    pipe.fit(feats)
    return pipe, rows, [pipe.encode_features(f) for f in feats]


def _add(store: ReferenceStore, rows, codes) -> list[int]:
    items = [
        NewReference(r.image.read_bytes(), "jpeg", r.lat, r.lon, float_code=c.float_, binary_code=c.binary)
        for r, c in zip(rows, codes, strict=True)
    ]
    return [i for i, _ in store.add_many(items)[0]]


def _copy_main_file(src, dest) -> None:
    """The database's main file alone, as a copy that forgets the -wal makes it."""
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copy2(src / DB_NAME, dest / DB_NAME)
    shutil.copytree(src / "images", dest / "images", dirs_exist_ok=True)


def _copy_snapshot(src, dest) -> None:
    for p in [src / MANIFEST, *src.glob("*.faiss")]:
        shutil.copy2(p, dest / p.name)


def test_the_database_id_is_in_the_main_file_from_the_start(tmp_path):
    store = ReferenceStore(tmp_path / "d")
    db_id = store.database_id
    assert db_id and len(db_id) == 32
    _copy_main_file(tmp_path / "d", tmp_path / "copy")  # while the store is open: the WAL stays behind
    con = sqlite3.connect(tmp_path / "copy" / DB_NAME)
    assert con.execute("SELECT value FROM meta WHERE key='database_id'").fetchone() == (db_id,)
    con.close()
    store.close()
    assert ReferenceStore(tmp_path / "d").database_id == db_id


def test_a_database_made_by_an_older_version_gets_an_id(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path)
    _add(store, rows[:2], codes[:2])
    store.db.execute("DELETE FROM meta WHERE key='database_id'")
    store.close()
    again = ReferenceStore(tmp_path)
    assert again.database_id and again.count() == 2


def test_a_snapshot_of_this_database_is_served(tmp_path, fitted):
    pipe, rows, codes = fitted
    writer = Collection(ReferenceStore(tmp_path), pipe)
    _add(writer.store, rows[:4], codes[:4])
    writer.write_snapshot()
    m = json.loads((tmp_path / MANIFEST).read_text())
    assert m["database_id"] == writer.store.database_id
    assert m["ref_high_water"] == 4 and m["last_change"][:2] == [4, "add"]
    _add(writer.store, rows[4:6], codes[4:6])
    reader = Collection(ReferenceStore(tmp_path), pipe)
    assert reader.stats.full_rebuilds == 0 and reader.stats.replayed_at_start == 2 and reader.size == 6


def test_a_snapshot_ahead_of_its_database_is_refused_and_its_ids_never_come_back(tmp_path, fitted):
    pipe, rows, codes = fitted
    orig, copy = tmp_path / "orig", tmp_path / "copy"
    writer = Collection(ReferenceStore(orig), pipe)
    _add(writer.store, rows[:3], codes[:3])
    writer.store.checkpoint()
    _copy_main_file(orig, copy)  # the main file holds 3 rows
    _add(writer.store, rows[3:8], codes[3:8])  # 5 more, in the WAL only
    writer.write_snapshot()
    _copy_snapshot(orig, copy)  # a snapshot of 8

    store = ReferenceStore(copy)
    with pytest.raises(SnapshotMismatch, match="ahead of the database"):
        check_binding(read_manifest_of(copy), store)
    served = Collection(store, pipe)
    assert served.stats.full_rebuilds == 1 and served.size == store.count() == 3
    new = _add(store, rows[8:10], codes[8:10])
    assert min(new) > 8, new  # ids 4..8 named other photos in the snapshot
    assert store.version > 8  # the change log never reaches the refused snapshot's version again
    served.catch_up()
    assert served.size == 5


def test_a_snapshot_of_another_database_is_refused(tmp_path, fitted):
    pipe, rows, codes = fitted
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):  # the same rows, ids and versions: only the identity tells them apart
        c = Collection(ReferenceStore(d), pipe)
        _add(c.store, rows[:3], codes[:3])
        c.write_snapshot()
    _copy_snapshot(a, b)
    store = ReferenceStore(b)
    with pytest.raises(SnapshotMismatch, match="made from database"):
        check_binding(read_manifest_of(b), store)
    assert Collection(store, pipe).stats.full_rebuilds == 1


def test_a_snapshot_whose_change_log_diverged_is_refused(tmp_path, fitted):
    pipe, rows, codes = fitted
    orig, copy = tmp_path / "orig", tmp_path / "copy"
    writer = Collection(ReferenceStore(orig), pipe)
    _add(writer.store, rows[:2], codes[:2])
    writer.store.checkpoint()
    _copy_main_file(orig, copy)
    _add(writer.store, rows[2:4], codes[2:4])
    writer.write_snapshot()  # version 4: refs 3 and 4
    other = ReferenceStore(copy)
    _add(other, rows[6:9], codes[6:9])  # the copy went on by itself to version 5: ids 3-5, other photos
    other.close()
    _copy_snapshot(orig, copy)
    store = ReferenceStore(copy)
    with pytest.raises(SnapshotMismatch, match="change log at version 4"):
        check_binding(read_manifest_of(copy), store)
    served = Collection(store, pipe)
    assert served.stats.full_rebuilds == 1 and served.size == 5


def test_a_snapshot_from_an_older_version_is_rebuilt_once(tmp_path, fitted):
    pipe, rows, codes = fitted
    writer = Collection(ReferenceStore(tmp_path), pipe)
    _add(writer.store, rows[:3], codes[:3])
    writer.write_snapshot()
    m = json.loads((tmp_path / MANIFEST).read_text())
    for key in ("database_id", "last_change", "ref_high_water"):
        del m[key]
    (tmp_path / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(SnapshotUnverifiable):
        check_binding(read_manifest_of(tmp_path), writer.store)
    served = Collection(ReferenceStore(tmp_path), pipe)
    assert served.stats.full_rebuilds == 1 and served.size == 3
    served.write_snapshot()
    assert Collection(ReferenceStore(tmp_path), pipe).stats.full_rebuilds == 0


def test_checkpoint_and_close_put_the_rows_in_the_main_file(tmp_path, fitted):
    pipe, rows, codes = fitted
    store = ReferenceStore(tmp_path / "d")
    keep_open = ReferenceStore(tmp_path / "d")  # another process's connection: closing store is not the last
    _add(store, rows[:4], codes[:4])
    busy, frames, done = store.checkpoint()
    assert (busy, frames) == (0, done)
    _copy_main_file(tmp_path / "d", tmp_path / "copy")
    assert ReferenceStore(tmp_path / "copy").count() == 4
    _add(store, rows[4:6], codes[4:6])
    store.close()  # TRUNCATE: the WAL is emptied although keep_open still has the database open
    assert (tmp_path / "d" / f"{DB_NAME}-wal").stat().st_size == 0
    keep_open.close()


def _mode(p) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_what_the_store_creates_is_private_whatever_the_umask(tmp_path, fitted):
    pipe, rows, codes = fitted
    old = os.umask(0o002)
    try:
        store = ReferenceStore(tmp_path / "d")
        _add(store, rows[:2], codes[:2])
        d = tmp_path / "d"
        assert _mode(d) == 0o700 and _mode(d / "images") == 0o700
        for p in [d / DB_NAME, d / f"{DB_NAME}-wal", d / f"{DB_NAME}-shm", *(d / "images").iterdir()]:
            assert _mode(p) == 0o600, p.name
        store.close()
    finally:
        os.umask(old)


def test_existing_files_keep_their_mode_and_keep_working(tmp_path, fitted):
    pipe, rows, codes = fitted
    old = os.umask(0o022)
    try:
        sqlite3.connect(tmp_path / DB_NAME).close()  # a database file made before this version: 0644
        assert _mode(tmp_path / DB_NAME) == 0o644
        store = ReferenceStore(tmp_path)
        assert _add(store, rows[:2], codes[:2]) == [1, 2]
        assert _mode(tmp_path / DB_NAME) == 0o644
        store.close()
    finally:
        os.umask(old)
