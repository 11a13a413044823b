"""The stored-features files: written whole or not at all, read per name, deleted, listed; real records."""

import hashlib
import os
import stat
import threading

import pytest

from app.engine import stored_features as sf
from app.engine.imageio import load_image
from app.engine.matchers.sift_mnn import features_for_verification
from app.storage.feature_files import FeatureFiles
from tests.conftest import penn_photo


@pytest.fixture(scope="module")
def records():
    """(sha256 of the image, its stored features' bytes) for three penn photos."""
    out = []
    for name in ("img_00000.jpg", "img_00001.jpg", "img_00002.jpg"):
        data = penn_photo(name).read_bytes()
        f = features_for_verification(load_image(data).rgb)
        out.append((hashlib.sha256(data).hexdigest(), sf.encode(sf.from_pixels(f.xy, f.descriptors, 800, 600))))
    return out


def test_write_read_delete_and_list(tmp_path, records):
    store = FeatureFiles(tmp_path / "features" / "rootsift-800-n1500")
    assert list(store.names()) == [] and store.read(records[0][0]) is None
    for sha, data in records:
        path = store.write(sha, data, sync=True)
        assert path == tmp_path / "features" / "rootsift-800-n1500" / sha[:3] / f"{sha}.lf"
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert sorted(store.names()) == sorted(sha for sha, _ in records)
    got = store.read_many([records[0][0], records[2][0], "0" * 64])
    assert set(got) == {records[0][0], records[2][0]}
    assert len(sf.decode(got[records[2][0]])) == len(sf.decode(records[2][1]))
    assert store.delete(records[1][0]) and not store.delete(records[1][0])
    assert not store.exists(records[1][0]) and store.read(records[1][0]) is None
    assert sorted(store.names()) == sorted([records[0][0], records[2][0]])


def test_a_rewrite_replaces_the_file_whole_and_leaves_no_temporary(tmp_path, records):
    store = FeatureFiles(tmp_path)
    sha = records[0][0]
    store.write(sha, records[1][1])
    store.write(sha, records[0][1])
    assert store.read(sha) == records[0][1]
    assert list(store.temporary_files()) == []


def test_an_interrupted_write_leaves_the_old_file_and_its_temporary_is_not_a_name(tmp_path, records, monkeypatch):
    store = FeatureFiles(tmp_path)
    sha, data = records[0]
    store.write(sha, data)

    def crash(src, dst):
        raise OSError("disk gone")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError, match="disk gone"):
        store.write(sha, records[1][1])
    monkeypatch.undo()
    assert store.read(sha) == data  # the reader still sees the whole old record
    assert list(store.temporary_files()) == []  # the failed write removed its temporary file
    leftover = store.path(sha).with_name(f".{sha}.lf.123.456.tmp")  # a crash (kill -9) leaves one
    leftover.write_bytes(b"half")
    assert list(store.names()) == [sha] and list(store.temporary_files()) == [leftover]


def test_concurrent_writers_of_one_name_leave_one_whole_record(tmp_path, records):
    store = FeatureFiles(tmp_path)
    sha = records[0][0]
    threads = [threading.Thread(target=store.write, args=(sha, records[i % 3][1])) for i in range(12)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert store.read(sha) in {data for _, data in records}
    sf.decode(store.read(sha))  # whole: the checksum holds


def test_names_must_be_sha256_digests(tmp_path):
    store = FeatureFiles(tmp_path)
    for bad in ("../../etc/passwd", "ABC" * 21 + "D", "0" * 63):
        with pytest.raises(ValueError, match="sha256"):
            store.path(bad)
