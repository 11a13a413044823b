"""Write-back on its own (no model): an existing sidecar keeps its other tags and comes back byte for byte
on undo; a photo named like an option never reaches exiftool's command line (it edits copies in the data
dir, each after "--"); nothing
is written for a rejected photo; undo never overwrites a later edit and goes on past a file it cannot
restore; a photo written and then rejected loses its written GPS at the next write."""

from __future__ import annotations

import hashlib
import shutil
import subprocess
from pathlib import Path

from app.library import writeback
from app.library.review import decide
from app.library.writeback import read_gps, undo, write_back
from app.storage.library import LOCATED, LibraryJournal
from tests.conftest import PENN
from tests.library.conftest import exiftool_ready


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_existing_sidecar_dash_names_and_undo(tmp_path, monkeypatch):
    exiftool_ready()
    lib = tmp_path / "lib"
    lib.mkdir()
    names = ("-dash.jpg", "tagged.jpg", "rejected.jpg")
    for name in names:
        shutil.copyfile(PENN / "photos" / "img_00036.jpg", lib / name)
    sidecar = lib / "tagged.jpg.xmp"
    subprocess.run(["exiftool", "-q", "-XMP-dc:Title=kept", str(sidecar)], check=True)  # another tool's sidecar
    before = {p.name: sha(p) for p in lib.iterdir()}
    j = LibraryJournal(tmp_path / "data")
    sid = j.start_scan(lib, 3)
    for name in names:
        result = {"file": str(lib / name), "placed": True, "confident": True, "lat": 39.9523, "lon": -75.1902}
        st = (lib / name).stat()  # as the scan saw it: a photo changed since is not written
        j.record(sid, lib / name, st.st_size, st.st_mtime_ns, LOCATED, result)
    ids = {r.path.split("/")[-1]: r.id for r in j.photos(sid)}
    decide(j, sid, ids["-dash.jpg"], "accept")
    decide(j, sid, ids["tagged.jpg"], "move", 39.95, -75.19)
    decide(j, sid, ids["rejected.jpg"], "reject")

    calls: list[list[str]] = []
    real_run = subprocess.run

    def run(cmd, *args, **kwargs):
        calls.append(list(cmd))
        return real_run(cmd, *args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(writeback.subprocess, "run", run)
        out = write_back(j, sid, tmp_path / "data")
    assert not out["failed"] and len(out["written"]) == 2, out
    assert len(calls) >= 4  # a write and a read-back per photo
    for cmd in calls:  # every file exiftool is given comes after "--", and it edits copies in the data dir
        files = [a for a in cmd if a.startswith(str(tmp_path))]
        assert all(f.startswith(str(tmp_path / "data")) for f in files), cmd
        assert files and cmd.index("--") < min(cmd.index(f) for f in files), cmd
    tool = shutil.which("exiftool")
    assert read_gps(tool, lib / "-dash.jpg.xmp") == (39.9523, -75.1902)
    assert read_gps(tool, sidecar) == (39.95, -75.19)
    title = subprocess.run(["exiftool", "-s3", "-XMP-dc:Title", str(sidecar)], capture_output=True, text=True)
    assert title.stdout.strip() == "kept"
    assert not (lib / "rejected.jpg.xmp").exists()
    assert all(sha(lib / n) == before[n] for n in names)  # the photos themselves: untouched

    assert len(undo(j, sid)["restored"]) == 2
    assert {p.name: sha(p) for p in lib.iterdir()} == before  # the other tool's sidecar as it was
    j.close()


def _library(tmp_path, names):
    lib = tmp_path / "lib"
    lib.mkdir()
    for name in names:
        shutil.copyfile(PENN / "photos" / "img_00036.jpg", lib / name)
    j = LibraryJournal(tmp_path / "data")
    sid = j.start_scan(lib, len(names))
    for name in names:
        result = {"file": str(lib / name), "placed": True, "confident": True, "lat": 39.9523, "lon": -75.1902}
        st = (lib / name).stat()  # as the scan saw it: a photo changed since is not written
        j.record(sid, lib / name, st.st_size, st.st_mtime_ns, LOCATED, result)
    ids = {Path(r.path).name: r.id for r in j.photos(sid)}
    for name in names:
        decide(j, sid, ids[name], "accept")
    return lib, j, sid, ids


def test_undo_skips_later_edits_and_goes_on_past_a_failure(tmp_path):
    exiftool_ready()
    lib, j, sid, _ = _library(tmp_path, ("a.jpg", "b.jpg", "c.jpg"))
    assert len(write_back(j, sid, tmp_path / "data")["written"]) == 3
    edited = lib / "a.jpg.xmp"
    edited.write_text(edited.read_text() + "<!-- the user's own edit -->")
    mine = edited.read_bytes()
    (lib / "b.jpg.xmp").unlink()  # gone since: nothing to restore
    write = next(w for w in j.live_writes(sid) if w["target"].endswith("c.jpg.xmp"))
    (lib / "c.jpg.xmp").unlink()
    (lib / "c.jpg.xmp").mkdir()  # a folder where our sidecar was: removing it raises OSError
    assert write["after_sha"] is not None
    # As if that write never finished (no hash: undo puts its backup back): removing the folder fails.
    j._db.execute("UPDATE writes SET after_sha=NULL WHERE id=?", (write["id"],))

    out = undo(j, sid)
    assert edited.read_bytes() == mine  # a later edit is never overwritten
    skipped = {Path(s["target"]).name: s["reason"] for s in out["skipped"]}
    assert "changed since" in skipped["a.jpg.xmp"] and "gone" in skipped["b.jpg.xmp"], out
    assert [Path(f["target"]).name for f in out["failed"]] == ["c.jpg.xmp"], out  # reported, not a crash
    assert out["restored"] == []
    j.close()


def test_a_write_withdrawn_by_a_later_decision_is_undone_at_the_next_write(tmp_path):
    exiftool_ready()
    lib, j, sid, ids = _library(tmp_path, ("a.jpg", "b.jpg"))
    assert len(write_back(j, sid, tmp_path / "data")["written"]) == 2
    decide(j, sid, ids["a.jpg"], "reject")
    decide(j, sid, ids["b.jpg"], "clear")
    dry = write_back(j, sid, tmp_path / "data", dry_run=True)
    assert sorted(Path(p).name for p in dry["withdrawn"]) == ["a.jpg", "b.jpg"] and (lib / "a.jpg.xmp").exists()
    out = write_back(j, sid, tmp_path / "data")
    assert sorted(Path(t).name for t in out["withdrawn"]["restored"]) == ["a.jpg.xmp", "b.jpg.xmp"], out
    assert not (lib / "a.jpg.xmp").exists() and not (lib / "b.jpg.xmp").exists()
    assert all(r.written is None for r in j.photos(sid))
    j.close()
