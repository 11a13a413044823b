"""Write-back on its own (no model): an existing sidecar keeps its other tags and comes back byte for byte
on undo; a photo named like an option is a file to exiftool; nothing is written for a rejected photo."""

from __future__ import annotations

import hashlib
import shutil
import subprocess

from app.library.review import decide
from app.library.writeback import read_gps, undo, write_back
from app.storage.library import LOCATED, LibraryJournal
from tests.conftest import PENN
from tests.library.conftest import exiftool_ready


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_existing_sidecar_dash_names_and_undo(tmp_path):
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
        j.record(sid, lib / name, 1, 1, LOCATED, result)
    ids = {r.path.split("/")[-1]: r.id for r in j.photos(sid)}
    decide(j, sid, ids["-dash.jpg"], "accept")
    decide(j, sid, ids["tagged.jpg"], "move", 39.95, -75.19)
    decide(j, sid, ids["rejected.jpg"], "reject")

    out = write_back(j, sid, tmp_path / "data")
    assert not out["failed"] and len(out["written"]) == 2, out
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
