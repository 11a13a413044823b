"""What the server may touch of its disk: the API scans folders under the library
root only (never a manifest, whose rows may name any file); a scan never follows a symbolic link; a write
or an undo refuses a linked target and, on the server, any target outside the root; thumbnails likewise;
scan ids are random; a scan left "running" by a dead process is marked interrupted at the next start."""

from __future__ import annotations

import os
import shutil
import threading
from concurrent.futures import ThreadPoolExecutor

import pytest

from app.engine.imageio import ImageLimits
from app.library.jobs import FolderRefused, LibraryJobs, ScanBusy
from app.library.photos import read_meta, walk_photos
from app.library.review import decide
from app.library.scan import bounded_map
from app.library.writeback import write_back
from app.storage.library import LOCATED, PROBLEM, JournalError, LibraryJournal
from tests.conftest import PENN
from tests.library.conftest import exiftool_ready

PHOTO = PENN / "photos" / "img_00036.jpg"


def test_the_api_takes_folders_under_the_root_only(tmp_path):
    root = tmp_path / "root"
    (root / "lib").mkdir(parents=True)
    (root / "lib" / "survey.csv").write_text("image,lat,lon,split\n/etc/passwd,0,0,query\n")
    jobs = LibraryJobs(tmp_path / "data", root)
    try:
        assert jobs.folder("lib") == (root / "lib").resolve()
        with pytest.raises(FolderRefused, match="not a folder"):
            jobs.folder("lib/survey.csv")  # a manifest names files anywhere: refused
        with pytest.raises(FolderRefused, match="library root"):
            jobs.folder("../")
        os.symlink(tmp_path, root / "out")  # a link leading out of the root
        with pytest.raises(FolderRefused, match="library root"):
            jobs.folder("out")
    finally:
        jobs.close()


def test_a_scan_never_follows_links(tmp_path):
    lib, outside = tmp_path / "lib", tmp_path / "outside"
    lib.mkdir()
    outside.mkdir()
    shutil.copyfile(PHOTO, lib / "a.jpg")
    shutil.copyfile(PHOTO, outside / "secret.jpg")
    os.symlink(outside / "secret.jpg", lib / "link.jpg")
    os.symlink(outside, lib / "linked-folder")
    assert walk_photos(lib) == [lib / "a.jpg"]


def _accepted(journal: LibraryJournal, sid: str, photo) -> int:
    result = {"file": str(photo), "placed": True, "confident": True, "lat": 39.9523, "lon": -75.1902}
    st = photo.stat()  # as the scan saw it: a photo changed since is not written
    journal.record(sid, photo, st.st_size, st.st_mtime_ns, LOCATED, result)
    rid = journal.known(sid)[str(photo)].id
    decide(journal, sid, rid, "accept")
    return rid


def test_writes_refuse_links_and_files_outside_the_root(tmp_path):
    exiftool_ready()
    root, outside = tmp_path / "root", tmp_path / "outside"
    (root / "lib").mkdir(parents=True)
    outside.mkdir()
    shutil.copyfile(PHOTO, root / "lib" / "a.jpg")
    shutil.copyfile(PHOTO, outside / "b.jpg")
    before = (outside / "b.jpg").read_bytes()
    os.symlink(outside / "b.jpg", root / "lib" / "linked.jpg")  # a link made after the scan
    (outside / "side.xmp").write_text("theirs")
    os.symlink(outside / "side.xmp", root / "lib" / "a.jpg.xmp")  # a linked sidecar
    j = LibraryJournal(tmp_path / "data")
    sid = j.start_scan(root / "lib", 3)
    _accepted(j, sid, root / "lib" / "a.jpg")
    _accepted(j, sid, root / "lib" / "linked.jpg")
    _accepted(j, sid, outside / "b.jpg")  # a journal row naming a file outside the root
    out = write_back(j, sid, tmp_path / "data", in_file=True, root=root.resolve())
    reasons = {os.path.basename(f["file"]): f["reason"] for f in out["failed"]}
    assert "symbolic link" in reasons["linked.jpg"] and "outside the library root" in reasons["b.jpg"], out
    assert (outside / "b.jpg").read_bytes() == before and (root / "lib" / "linked.jpg").is_symlink()
    side = write_back(j, sid, tmp_path / "data", root=root.resolve())  # sidecars: a.jpg's is a link
    assert "a.jpg.xmp is a symbolic link" in str(side["failed"]), side
    assert (outside / "side.xmp").read_text() == "theirs" and (root / "lib" / "a.jpg.xmp").is_symlink()
    j.close()


def test_thumbnails_read_regular_files_under_the_root_only(tmp_path):
    root, outside = tmp_path / "root", tmp_path / "outside"
    root.mkdir()
    outside.mkdir()
    shutil.copyfile(PHOTO, root / "a.jpg")
    shutil.copyfile(PHOTO, outside / "b.jpg")
    os.symlink(outside / "b.jpg", root / "link.jpg")
    jobs = LibraryJobs(tmp_path / "data", root)
    try:
        limits = ImageLimits()
        assert jobs.thumbnail(root / "a.jpg", 64, limits)[:2] == b"\xff\xd8"
        for path in (root / "link.jpg", outside / "b.jpg"):
            with pytest.raises(FileNotFoundError):
                jobs.thumbnail(path, 64, limits)
    finally:
        jobs.close()


def test_scan_ids_are_random_and_found_by_folder(tmp_path):
    a, b = LibraryJournal(tmp_path / "a"), LibraryJournal(tmp_path / "b")
    ids = {a.start_scan(tmp_path, 0), b.start_scan(tmp_path, 0)}
    assert len(ids) == 2 and all(len(i) == 16 and int(i, 16) >= 0 for i in ids)  # not derived from the path
    assert a.start_scan(tmp_path, 0) == a.scan_of(tmp_path) and a.scan_of(tmp_path / "x") is None
    a.close()
    b.close()


def test_a_scan_left_running_is_interrupted_at_start(tmp_path):
    j = LibraryJournal(tmp_path / "data")
    sid = j.start_scan(tmp_path, 10)  # then the process is killed
    j.close()
    jobs = LibraryJobs(tmp_path / "data", tmp_path)
    try:
        got = jobs.journal.scan(sid)
        assert got["state"] == "interrupted" and "scan again" in got["message"]
    finally:
        jobs.close()


def test_one_scan_write_or_undo_at_a_time(tmp_path):
    jobs = LibraryJobs(tmp_path / "data", tmp_path)
    try:
        with jobs.exclusive("0123456789abcdef"):
            with pytest.raises(ScanBusy), jobs.exclusive("0123456789abcdef"):
                pass
            with jobs.exclusive("fedcba9876543210"):  # another library is not held up
                pass
    finally:
        jobs.close()


def test_the_pool_gets_a_bounded_window_and_a_stop_ends_submission():
    started: list[int] = []
    stop = threading.Event()

    def work(n: int) -> int:
        started.append(n)
        return n

    with ThreadPoolExecutor(2) as pool:
        got = []
        for n in bounded_map(pool, work, range(1000), 4, stop):
            got.append(n)
            if n == 9:
                stop.set()
    assert got[:10] == list(range(10)) and len(started) <= 10 + 4, len(started)


def test_a_file_name_that_is_not_utf8_is_a_problem_not_a_failed_scan(tmp_path):
    lib = tmp_path / "lib"
    lib.mkdir()
    shutil.copyfile(PHOTO, lib / "a.jpg")
    raw = os.path.join(os.fsencode(lib), b"caf\xe9.jpg")  # Latin-1 bytes: not UTF-8
    shutil.copyfile(PHOTO, raw)
    paths = walk_photos(lib)
    assert len(paths) == 2
    metas = [read_meta(p) for p in paths]
    bad = next(m for m in metas if m.problem)
    assert "not UTF-8" in bad.problem and bad.path.name == "caf\ufffd.jpg"
    j = LibraryJournal(tmp_path / "data")
    sid = j.start_scan(lib, 2)
    j.record(sid, bad.path, 0, 0, PROBLEM, {"file": str(bad.path), "reason": bad.problem})  # the journal takes it
    assert [r.kind for r in j.photos(sid)] == [PROBLEM]
    j.close()


def test_a_parent_and_its_sub_folder_keep_their_own_rows(tmp_path):
    (tmp_path / "sub").mkdir()
    j = LibraryJournal(tmp_path / "data")
    parent, sub = j.start_scan(tmp_path, 1), j.start_scan(tmp_path / "sub", 1)
    photo = tmp_path / "sub" / "a.jpg"
    j.record(parent, photo, 1, 1, LOCATED, {"file": str(photo), "placed": False})
    j.record(sub, photo, 1, 1, LOCATED, {"file": str(photo), "placed": False})  # keyed by (scan, path)
    assert len(j.photos(parent)) == 1 and len(j.photos(sub)) == 1
    j.close()


def test_a_journal_of_the_first_layout_is_refused_in_one_line(tmp_path):
    import sqlite3
    import subprocess
    import sys

    data = tmp_path / "data"
    data.mkdir()
    old = sqlite3.connect(data / "library.sqlite")  # schema 1: photos keyed by path alone, no user_version
    old.execute("CREATE TABLE photos (id INTEGER PRIMARY KEY, scan TEXT, path TEXT NOT NULL UNIQUE)")
    old.commit()
    old.close()
    with pytest.raises(JournalError, match="older library journal"):
        LibraryJournal(data)
    args = [sys.executable, "-m", "app.cli", "library", "list", str(tmp_path), "--data-dir", str(data)]
    p = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "older library journal" in p.stderr and "Traceback" not in p.stderr, p.stderr
