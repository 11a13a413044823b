"""What the library does with a user's files when they change under it, on their own (no model): a write
never goes through a folder that became a link, nor into a photo replaced since it was located; a failed
write leaves no temporary file in the user's folder; undo after a crash (the process killed at the worst
moments) never overwrites a later edit nor deletes another tool's sidecar; a position this service wrote
is marked as its estimate and never read back as a measured one; pipes, links and devices are refused
before anything waits on them."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from app.domain import Upload
from app.engine.errors import NoGpsInImage
from app.engine.imageio import ImageLimits, load_image
from app.ingestion.uploads import prepare_upload
from app.library.photos import read_meta
from app.library.review import decide
from app.library.writeback import WriteBackError, open_folder, read_gps, undo, write_back
from app.storage.library import LOCATED, LibraryJournal
from app.user_files import NotARegularFile, read_regular
from tests.conftest import PENN, REPO
from tests.library.conftest import exiftool_ready

PHOTO, OTHER = PENN / "photos" / "img_00036.jpg", PENN / "photos" / "img_00042.jpg"
AT = (39.9523, -75.1902)


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def accepted_library(
    tmp_path: Path, folder: Path, names: tuple[str, ...], scanned: Path | None = None
) -> tuple[LibraryJournal, str]:
    """``names`` in ``folder`` (copies of a penn photo), journalled as a scan of ``scanned`` (default: the
    folder) leaves them, each accepted."""
    folder.mkdir(parents=True, exist_ok=True)
    j = LibraryJournal(tmp_path / "data")
    sid = j.start_scan(scanned or folder, len(names))
    for name in names:
        path = folder / name
        if not path.exists():
            shutil.copyfile(PHOTO, path)
        st = path.stat()
        result = {"file": str(path), "placed": True, "confident": True, "lat": AT[0], "lon": AT[1]}
        j.record(sid, path, st.st_size, st.st_mtime_ns, LOCATED, result)
    for rec in j.photos(sid):
        decide(j, sid, rec.id, "accept")
    return j, sid


def test_the_cli_never_writes_through_a_folder_made_a_link(tmp_path):
    exiftool_ready()
    lib, outside = tmp_path / "lib", tmp_path / "outside"
    j, _ = accepted_library(tmp_path, lib / "sub", ("a.jpg", "b.jpg"), scanned=lib)
    j.close()
    outside.mkdir()
    for name in ("a.jpg", "b.jpg"):  # the same bytes and times: only the folder differs
        shutil.copy2(lib / "sub" / name, outside / name)
    before = {n: sha(outside / n) for n in ("a.jpg", "b.jpg")}
    shutil.rmtree(lib / "sub")
    os.symlink(outside, lib / "sub")
    args = ["library", "write", str(lib), "--in-file", "--data-dir", str(tmp_path / "data")]
    p = subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=300)
    assert {n: sha(outside / n) for n in before} == before, p.stdout + p.stderr
    assert "symbolic link in its path" in p.stdout and "0 wrote, 2 failed" in p.stdout, p.stdout + p.stderr


def test_a_photo_replaced_since_it_was_located_is_not_written(tmp_path):
    exiftool_ready()
    lib = tmp_path / "lib"
    j, sid = accepted_library(tmp_path, lib, ("a.jpg", "b.jpg"))
    shutil.copyfile(OTHER, lib / "b.jpg")  # another picture under the reviewed name
    replaced = sha(lib / "b.jpg")
    out = write_back(j, sid, tmp_path / "data", in_file=True)
    assert [Path(w["file"]).name for w in out["written"]] == ["a.jpg"], out
    assert [Path(f["file"]).name for f in out["failed"]] == ["b.jpg"] and "changed since" in out["failed"][0]["reason"]
    assert sha(lib / "b.jpg") == replaced  # the other picture keeps its own GPS
    j.close()


def test_a_failed_write_leaves_nothing_in_the_users_folder(tmp_path):
    exiftool_ready()
    lib = tmp_path / "lib"
    j, sid = accepted_library(tmp_path, lib, ("a.jpg", "b.jpg"))
    if subprocess.run(["chattr", "+i", str(lib / "a.jpg")], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not supported on this file system")
    try:
        out = write_back(j, sid, tmp_path / "data", in_file=True)
    finally:
        subprocess.run(["chattr", "-i", str(lib / "a.jpg")], check=True)
    assert [Path(f["file"]).name for f in out["failed"]] == ["a.jpg"], out
    assert sorted(os.listdir(lib)) == ["a.jpg", "b.jpg"]  # no hidden copy left beside the photo
    assert sha(lib / "a.jpg") == sha(PHOTO)
    assert not list((tmp_path / "data" / "library-staging").iterdir())
    assert len(undo(j, sid)["restored"]) == 1 and sha(lib / "b.jpg") == sha(PHOTO)
    j.close()


CRASH = """
import os, signal, sys
from pathlib import Path
from app.library import writeback
from app.storage.library import LibraryJournal

where, in_file, data, folder = sys.argv[1], sys.argv[2] == "1", Path(sys.argv[3]), Path(sys.argv[4])

def die(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)

if where == "exiftool":  # the first exiftool call: the edit itself
    writeback.subprocess.run = die
else:  # the rename that puts the written file in place
    writeback.os.replace = die
j = LibraryJournal(data)
writeback.write_back(j, j.scan_of(folder), data, in_file=in_file)
"""


@pytest.mark.crash
@pytest.mark.parametrize("where", ["exiftool", "rename"])
def test_undo_after_a_crashed_write_keeps_later_edits(tmp_path, where):
    exiftool_ready()
    lib = tmp_path / "lib"
    j, sid = accepted_library(tmp_path, lib, ("a.jpg", "b.jpg"))
    j.close()
    for in_file in ("1", "0"):  # a.jpg in the photo itself, then b.jpg's sidecar
        if in_file == "0":
            j = LibraryJournal(tmp_path / "data")
            decide(j, sid, j.known(sid)[str(lib / "a.jpg")].id, "clear")
            j.close()
        args = [sys.executable, "-c", CRASH, where, in_file, str(tmp_path / "data"), str(lib)]
        p = subprocess.run(args, capture_output=True, text=True, timeout=300, cwd=REPO)
        assert p.returncode == -signal.SIGKILL, p.stderr
    # After the crashes, the user edits the photo and another tool makes the sidecar.
    subprocess.run(
        ["exiftool", "-q", "-overwrite_original", "-XMP-dc:Title=mine", "--", str(lib / "a.jpg")], check=True
    )
    subprocess.run(["exiftool", "-q", "-XMP-dc:Title=theirs", "--", str(lib / "b.jpg.xmp")], check=True)
    edited, theirs = sha(lib / "a.jpg"), sha(lib / "b.jpg.xmp")
    j = LibraryJournal(tmp_path / "data")
    out = undo(j, sid)
    assert sha(lib / "a.jpg") == edited and (lib / "b.jpg.xmp").exists() and sha(lib / "b.jpg.xmp") == theirs, out
    assert sorted(os.listdir(lib)) == ["a.jpg", "b.jpg", "b.jpg.xmp"]  # no hidden file left behind
    j.close()


def test_a_position_we_wrote_is_never_read_as_measured(tmp_path):
    exiftool_ready()
    lib = tmp_path / "lib"
    j, sid = accepted_library(tmp_path, lib, ("a.jpg",))
    assert read_meta(lib / "a.jpg").gps is not None  # the original's own GPS: measured
    assert len(write_back(j, sid, tmp_path / "data", in_file=True)["written"]) == 1
    assert read_gps(shutil.which("exiftool"), lib / "a.jpg") == pytest.approx(AT)  # written, and readable
    meta = read_meta(lib / "a.jpg")
    assert meta.gps is None and "estimate" in meta.note, meta
    data = (lib / "a.jpg").read_bytes()
    assert load_image(data).gps is None and load_image(data).gps_estimated
    with pytest.raises(NoGpsInImage, match="estimated by this service"):
        prepare_upload(Upload(data, "a.jpg"), ImageLimits())
    sidecar = write_back(j, sid, tmp_path / "data")  # the sidecar says so too
    assert len(sidecar["written"]) == 1 and "geoloc-estimate" in (lib / "a.jpg.xmp").read_text()
    j.close()


def test_pipes_links_and_folders_are_refused_before_any_wait(tmp_path):
    lib, outside = tmp_path / "lib", tmp_path / "outside"
    lib.mkdir()
    outside.mkdir()
    shutil.copyfile(PHOTO, outside / "secret.jpg")
    os.mkfifo(lib / "pipe.jpg")  # opening it for reading would wait for a writer for ever
    os.symlink(outside / "secret.jpg", lib / "link.jpg")
    (lib / "folder.jpg").mkdir()
    for name in ("pipe.jpg", "link.jpg", "folder.jpg"):
        with pytest.raises(NotARegularFile):
            read_regular(lib / name, within=lib)
        assert read_meta(lib / name, lib.resolve()).problem, name
    assert read_regular(outside / "secret.jpg") == PHOTO.read_bytes()  # no folder to stay in: any file
    with pytest.raises(NotARegularFile, match="outside"):  # a link in a parent is seen on the descriptor
        os.symlink(outside, lib / "linked")
        read_regular(lib / "linked" / "secret.jpg", within=lib.resolve())


def test_nothing_is_written_inside_the_data_dir(tmp_path):
    data = tmp_path / "data"
    (data / "images").mkdir(parents=True)
    with pytest.raises(WriteBackError, match="data dir"):
        open_folder((data / "images").resolve(), None, data)


def test_an_unusable_journal_is_said_in_one_line(tmp_path):
    import sqlite3

    cases = {"random": None, "newer": "PRAGMA user_version=99", "other": "CREATE TABLE photos (x TEXT)"}
    for name, sql in cases.items():
        data = tmp_path / name
        data.mkdir()
        if sql is None:
            (data / "library.sqlite").write_bytes(os.urandom(8192))
        else:
            db = sqlite3.connect(data / "library.sqlite")
            db.execute("PRAGMA user_version=3" if name == "other" else sql)
            if name == "other":
                db.execute(sql)
            db.commit()
            db.close()
        args = [sys.executable, "-m", "app.cli", "library", "list", str(tmp_path), "--data-dir", str(data)]
        p = subprocess.run(args, capture_output=True, text=True, timeout=300)
        said = "newer version" if name == "newer" else "library journal"
        assert p.returncode == 2 and said in p.stderr and "Traceback" not in p.stderr, (name, p.stderr)
