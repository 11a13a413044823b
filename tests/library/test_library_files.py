"""A library whose files change under a scan, on a real server and the real CLI with the fitted default
pipeline: a file swapped for a link between the listing and the reads never joins the collection; a
named pipe is a problem file, never waited on; photos this service located and wrote GPS into are never
references, whichever library meets them again; a data dir inside the library root is never scanned nor
written; bad folder names and an unusable journal get a clear 4xx or 503, never a 500."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from app.engine.configs import DEFAULT_CONFIG
from app.ingestion.bulk import IngestOptions, ingest
from app.library.scan import PathsSource, ScanOptions, library_files, scan_library
from app.storage.library import LibraryJournal
from app.usecases.service import GeolocService
from tests.conftest import PENN
from tests.library.conftest import copy_collection, exiftool_ready
from tools.server_process import ServerProcess

pytestmark = pytest.mark.library
KEY = "library-files-key"


def wait_scan(c, sid: str, timeout_s: float = 600) -> dict:
    """The scan's state once it is no longer running (the test fails if it never ends)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = c.get(f"/library/scans/{sid}").json()
        if state["state"] != "running":
            return state
        time.sleep(0.2)
    pytest.fail(f"library scan {sid} still running after {timeout_s} s")


def strip_gps(paths: list[Path]) -> None:
    subprocess.run(["exiftool", "-q", "-overwrite_original", "-gps:all=", *map(str, paths)], check=True)


@pytest.fixture(scope="module")
def server(tmp_path_factory, library_models, query_truth, penn_collection):
    """A server whose data dir lies inside its library root, with two photos without GPS in nest/sub."""
    exiftool_ready()
    root = tmp_path_factory.mktemp("library-root")
    copy_collection(penn_collection, root / "data")
    sub = root / "nest" / "sub"
    sub.mkdir(parents=True)
    for name in sorted(query_truth)[:2]:
        shutil.copyfile(PENN / "photos" / name, sub / name)
    strip_gps(list(sub.iterdir()))
    env = {"GEOLOC_ORT_THREADS": "1", "GEOLOC_LIBRARY_ROOT": str(root)}
    s = ServerProcess(root / "data", library_models, DEFAULT_CONFIG, api_key=KEY, extra_env=env)
    try:
        s.wait_ready()
        s.root = root
        s.client.headers["X-API-Key"] = KEY
        yield s
    finally:
        s.stop()


def test_bad_folder_names_are_refused_in_words(server):
    c = server.client
    for folder, said in (("nest/\u0000", "NUL"), ("x" * 300, "too long"), ("data/images", "data dir")):
        r = c.post("/library/scans", json={"folder": folder})
        assert r.status_code == 422 and said in r.json()["message"], (folder[:20], r.status_code, r.text)


def scan(server, folder: str) -> dict:
    r = server.client.post("/library/scans", json={"folder": folder})
    assert r.status_code == 202, r.text
    state = wait_scan(server.client, r.json()["id"])
    assert state["state"] == "done", state
    return state


def test_located_photos_written_back_never_become_references(server):
    c = server.client
    size = c.get("/ready").json()["index_size"]
    sub = scan(server, "nest/sub")
    assert len(sub["photos"]) == 2 and all(p["kind"] == "located" for p in sub["photos"]), sub
    for p in sub["photos"]:
        moved = {"action": "move", "lat": 39.9523, "lon": -75.1902}  # a position the user chose
        assert c.post(f"/library/scans/{sub['id']}/photos/{p['id']}/decision", json=moved).status_code == 200
    wrote = c.post(f"/library/scans/{sub['id']}/write", json={"in_file": True}).json()
    assert len(wrote["written"]) == 2 and not wrote["failed"], wrote
    nest = scan(server, "nest")  # the same photos, met again by another library
    assert sorted(p["kind"] for p in nest["photos"]) == ["located", "located"], nest
    assert c.get("/ready").json()["index_size"] == size  # the guessed positions joined nothing

    backups = server.root / "data" / "library-backups"
    kept = {p.name: p.read_bytes() for p in backups.iterdir()}
    scan(server, ".")  # the root holds the data dir: its images and backups are no photos
    journal = LibraryJournal(server.root / "data")
    try:
        sid = journal.scan_of(server.root)
        paths = [Path(r.path) for r in journal.photos(sid)]
    finally:
        journal.close()
    assert paths and not [p for p in paths if (server.root / "data") in p.parents], paths
    assert {p.name: p.read_bytes() for p in backups.iterdir()} == kept


def test_an_unusable_journal_is_a_503_not_a_500(tmp_path, library_models):
    data = tmp_path / "data"
    data.mkdir()
    (data / "library.sqlite").write_bytes(os.urandom(8192))
    env = {"GEOLOC_ORT_THREADS": "1", "GEOLOC_LIBRARY_ROOT": str(tmp_path)}
    with ServerProcess(data, library_models, DEFAULT_CONFIG, api_key=KEY, extra_env=env) as s:
        key = {"X-API-Key": KEY}
        for r in (s.client.get("/library/scans/0123456789abcdef", headers=key),
                  s.client.post("/library/scans", json={"folder": "."}, headers=key)):  # fmt: skip
            assert r.status_code == 503 and "not a library journal" in r.json()["message"], r.text
        assert s.client.get("/ready").status_code == 200  # the rest of the service is unaffected


def test_a_named_pipe_is_a_problem_file_never_waited_on(tmp_path, library_models, penn_collection, query_truth):
    lib = tmp_path / "lib"
    lib.mkdir()
    ref = next(p for p in sorted((PENN / "photos").glob("*.jpg")) if p.name not in query_truth)
    shutil.copyfile(ref, lib / "a.jpg")  # a reference the collection holds already
    os.mkfifo(lib / "b.jpg")
    common = ["--models-dir", str(library_models), "--config", DEFAULT_CONFIG]
    d1, d2 = (copy_collection(penn_collection, tmp_path / d) for d in ("d1", "d2"))
    for args in (["library", "scan", str(lib), "--data-dir", str(d1)], ["ingest", str(lib), "--data-dir", str(d2)]):
        p = subprocess.run([sys.executable, "-m", "app.cli", *args, *common], capture_output=True, text=True,
                           timeout=300)  # fmt: skip
        assert p.returncode == 0 and "not a regular file" in p.stdout + p.stderr, p.stdout + p.stderr


def test_a_file_swapped_for_a_link_after_the_listing_is_never_read(
    tmp_path, library_models, penn_collection, query_truth
):
    lib, outside = tmp_path / "lib", tmp_path / "outside"
    lib.mkdir()
    outside.mkdir()
    refs = [p for p in sorted((PENN / "photos").glob("*.jpg")) if p.name not in query_truth]
    shutil.copyfile(refs[0], lib / "a.jpg")
    shutil.copyfile(refs[1], lib / "zzzz.jpg")
    secret = outside / "secret.jpg"  # a private GPS photo the collection does not hold
    shutil.copyfile(PENN / "photos" / sorted(query_truth)[0], secret)
    secret.chmod(0o600)
    data = copy_collection(penn_collection, tmp_path / "data")
    service = GeolocService.open(data, library_models, DEFAULT_CONFIG)
    journal = LibraryJournal(data)
    try:
        size = service.collection.size
        files = library_files(lib.resolve(), data.resolve())  # the listing: two regular files
        (lib / "zzzz.jpg").unlink()
        os.symlink(secret, lib / "zzzz.jpg")  # then swapped before they are read
        summary = scan_library(service, lib, ScanOptions(workers=1), journal, say=lambda _: None, files=files)
        assert service.collection.size == size and summary.added == 0, summary
        problems = dict(summary.problems)
        assert "symbolic link" in problems[str(lib.resolve() / "zzzz.jpg")], problems
        # The ingest step reads each file once more: a swap after the headers were read is refused there.
        source = PathsSource("folder", lib.resolve(), within=lib.resolve(), paths=(lib.resolve() / "zzzz.jpg",))
        got, _ = ingest(service, source, IngestOptions(workers=1), say=lambda _: None)
        assert got.added == 0 and service.collection.size == size, got
    finally:
        journal.close()
