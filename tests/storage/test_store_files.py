"""Image files and rows as one decision: an upload racing a delete of the same bytes, a delete whose file
cannot be removed (queued, retried), orphan files swept by age."""

import os
import shutil
import subprocess
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from app.errors import StorageUnavailable
from app.storage.orphans import retry_removals, sweep
from app.storage.store import NewReference, ReferenceStore
from tests.conftest import PENN

#: Every test here runs on SQLite and on PostgreSQL (the ``backend`` fixture).
pytestmark = pytest.mark.usefixtures("backend")

CROPS = sorted((PENN / "crops").glob("img_0000*_0.jpg"))
HOUR = 3600


def _item(path: Path = CROPS[0]) -> NewReference:
    return NewReference(path.read_bytes(), "jpeg", 39.95, -75.19, label=path.name)


@contextmanager
def immutable(folder: Path):
    """Make unlinking (and creating) in ``folder`` fail even for root, which ignores permission bits:
    ``chattr +i`` (ext4, xfs, btrfs). A read-only bind mount would need mount privileges."""
    assert shutil.which("chattr"), "chattr (e2fsprogs) is needed to make a folder unwritable for root"
    subprocess.run(["chattr", "+i", str(folder)], check=True)
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", str(folder)], check=True)


def _age(path: Path, seconds: float) -> None:
    t = time.time() - seconds
    os.utime(path, (t, t))


def _race(adder: ReferenceStore, deleter: ReferenceStore, ref_id: int) -> tuple[int, bool]:
    start = threading.Barrier(2)
    out: dict = {}

    def add():
        start.wait()
        out["add"] = adder.add_many([_item()])[0][0]

    def delete():
        start.wait()
        deleter.delete(ref_id)

    threads = [threading.Thread(target=add), threading.Thread(target=delete)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return out["add"]


def test_an_upload_racing_a_delete_of_the_same_image_keeps_its_file(tmp_path):
    """Two stores on one data dir (two processes' connections): one adds bytes already stored while the
    other deletes the row holding them. Whatever the order, a row the add created names a file on disk."""
    adder, deleter = ReferenceStore(tmp_path), ReferenceStore(tmp_path)
    lost = []
    for n in range(40):
        ((ref_id, _),), _ = adder.add_many([_item()])
        new_id, created = _race(adder, deleter, ref_id)
        if created and not adder.image_path(new_id).exists():
            lost.append(n)
    assert lost == [], f"rounds whose accepted upload has no image file: {lost}"
    assert adder.queued_removals() == []


def test_a_delete_whose_file_cannot_be_removed_queues_the_removal(tmp_path):
    store = ReferenceStore(tmp_path)
    (a, _), (b, _) = store.add_many([_item(CROPS[0]), _item(CROPS[1])])[0]
    path_a, path_b = store.image_path(a), store.image_path(b)
    with immutable(store.images_dir):
        with pytest.raises(OSError):  # the condition is real: root cannot unlink there
            os.unlink(path_a)
        assert store.delete(a) == "queued" and store.delete(b) == "queued"
        assert store.get(a) is None and store.get(b) is None  # the delete has happened
        assert path_a.exists() and sorted(store.queued_removals()) == sorted([path_a.name, path_b.name])
        removed, failed = retry_removals(store)  # still unwritable: both stay queued
        assert removed == [] and sorted(failed) == sorted([path_a.name, path_b.name])
        assert len(store.queued_removals()) == 2
    # The same bytes uploaded again meanwhile: the name is in use again, its removal is dropped.
    ((again, created),), _ = store.add_many([_item(CROPS[1])])
    assert created and store.queued_removals() == [path_a.name]
    removed, failed = retry_removals(store)
    assert removed == [path_a.name] and failed == [] and store.queued_removals() == []
    assert not path_a.exists() and store.image_path(again).exists()
    assert store.delete(again) == "removed" and not path_b.exists()


def test_an_add_into_an_unwritable_folder_stores_nothing(tmp_path):
    store = ReferenceStore(tmp_path)
    with immutable(store.images_dir), pytest.raises(StorageUnavailable):
        store.add_many([_item()])
    assert store.count(None) == 0 and list(store.images_dir.iterdir()) == []


def test_the_sweep_removes_old_orphans_and_keeps_young_ones(tmp_path):
    store = ReferenceStore(tmp_path)
    ((kept, _),), _ = store.add_many([_item(CROPS[0])])
    _age(store.image_path(kept), 2 * HOUR)  # an old file a row names: never touched
    old = store.images_dir / f"{NewReference(CROPS[1].read_bytes(), 'jpeg', 0, 0).sha256}.jpeg"
    young = store.images_dir / f"{NewReference(CROPS[2].read_bytes(), 'jpeg', 0, 0).sha256}.jpeg"
    tmp = store.images_dir / ".abc.jpeg.123.456.tmp"
    fresh_tmp = store.images_dir / ".def.jpeg.123.456.tmp"
    for src, dst in ((CROPS[1], old), (CROPS[2], young), (CROPS[3], tmp), (CROPS[4], fresh_tmp)):
        shutil.copy(src, dst)
    _age(old, 2 * HOUR)
    _age(tmp, 2 * HOUR)
    r = sweep(store, HOUR)
    assert r.removed == [old.name] and r.removed_tmp == [tmp.name] and r.young == [young.name] and not r.failed
    assert not old.exists() and not tmp.exists() and young.exists() and fresh_tmp.exists()
    assert store.image_path(kept).exists()
    # An upload of an old orphan's bytes that found the file and skipped writing it, swept before its
    # rows commit: the add writes the file again under the write lock.
    _age(young, 2 * HOUR)
    item = _item(CROPS[2])
    store.write_images([item])  # found: not written
    assert sweep(store, HOUR).removed == [young.name] and not young.exists()
    ((ref, created),), _ = store.insert_rows([item])
    assert created and store.image_path(ref).read_bytes() == CROPS[2].read_bytes()
