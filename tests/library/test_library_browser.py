"""The Library view in a real browser (Debian's Chromium, as tests/api/test_browser.py drives it), over
a real uvicorn server: the user scans a library folder on the page, accepts two suggestions and rejects
one, and writes: the two have XMP sidecars holding the accepted GPS, the rejected one has nothing, and the
originals are byte for byte (and pixel for pixel) what they were. A second scan skips what is done; undo
on the page restores every file. The API's own answers (a bad folder, a bad decision) are checked too."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from app.engine.configs import DEFAULT_CONFIG
from app.library.writeback import pixel_hash
from tests.api.test_browser import SHOTS, open_page
from tests.library.conftest import SF, copy_collection, make_library
from tools.server_process import ServerProcess

pytestmark = [pytest.mark.browser, pytest.mark.library]
KEY = "library-key"
HOSTILE = '<img src=x onerror="window.__xss=1">.jpg'


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def server(tmp_path_factory, library_models, query_truth, penn_collection):
    root = tmp_path_factory.mktemp("library-root")
    make_library(root / "library", query_truth)
    copy_collection(penn_collection, root / "data")  # the references: already encoded
    shutil.copyfile(SF / "q3.jpg", root / "library" / HOSTILE)  # a file name that is HTML: shown as text
    s = ServerProcess(
        root / "data",
        library_models,
        DEFAULT_CONFIG,
        api_key=KEY,
        extra_env={"GEOLOC_ORT_THREADS": "1", "GEOLOC_LIBRARY_ROOT": str(root)},
    )
    try:  # a server that never got ready is stopped all the same (no process left behind)
        s.wait_ready()
        s.library = root / "library"
        yield s
    finally:
        s.stop()


@pytest.fixture(scope="module")
def rootless(tmp_path_factory, library_models):
    """A server with no GEOLOC_LIBRARY_ROOT (the default): its API scans no folder. An empty data dir: the
    page is all that is looked at."""
    s = ServerProcess(tmp_path_factory.mktemp("no-library-root") / "data", library_models, DEFAULT_CONFIG,
                      api_key=KEY, extra_env={"GEOLOC_ORT_THREADS": "1"})  # fmt: skip
    try:
        s.wait_ready()
        yield s
    finally:
        s.stop()


def test_a_server_that_scans_no_folder_says_so_and_offers_no_scan(browser, rootless):
    page = open_page(browser, rootless, "desktop", None)
    page.goto(rootless.url + "/library")
    page.wait_for_function("() => !document.getElementById('scan-off').hidden")
    assert not page.locator("#scan-btn").is_visible() or page.locator("#scan-btn").is_disabled()
    note = page.inner_text("#scan-off")
    assert "scans no folder" in note and "GEOLOC_LIBRARY_ROOT" in note, note
    # Its API says the same (the page hides nothing the API would do).
    refused = rootless.client.post("/library/scans", json={"folder": "x"}, headers={"X-API-Key": KEY})
    assert refused.status_code == 422 and "GEOLOC_LIBRARY_ROOT" in refused.json()["message"]

    # The header has every view, as the main page's has: Locate a photo, References, Library.
    tabs = page.locator("header nav .tab")
    assert tabs.all_inner_texts() == ["Locate a photo", "References", "Library"]
    page.locator("header nav a.tab", has_text="References").click()
    page.wait_for_function("() => document.getElementById('tab-refs')?.getAttribute('aria-selected') === 'true'")
    assert page.url.startswith(rootless.url + "/") and page.locator("#view-refs").is_visible()
    assert not page.locator("#view-locate").is_visible()
    page.locator("header a.tab", has_text="Library").click()  # and back, as the main page links to it
    page.wait_for_url(rootless.url + "/library")
    page.locator("header nav a.tab", has_text="Locate a photo").click()
    page.wait_for_function("() => document.getElementById('tab-locate')?.getAttribute('aria-selected') === 'true'")
    assert page.locator("#view-locate").is_visible()
    assert not page.errors and page.evaluate("window.__csp") == []


def test_a_server_with_a_library_root_offers_the_scan(browser, server):
    page = open_page(browser, server, "desktop", None)
    page.goto(server.url + "/library")
    assert page.locator("#scan-btn").is_visible() and page.locator("#scan-btn").is_enabled()
    assert page.locator("#scan-off").count() == 0 or not page.locator("#scan-off").is_visible()
    assert page.locator("header nav a.tab", has_text="References").get_attribute("href") == "/#references"
    assert not page.errors and page.evaluate("window.__csp") == []


def wait_scan(c, sid: str, timeout_s: float = 900) -> dict:
    """The scan's state once it is no longer running (the test fails if it never ends)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = c.get(f"/library/scans/{sid}", headers={"X-API-Key": KEY}).json()
        if state["state"] != "running":
            return state
        time.sleep(0.2)
    pytest.fail(f"library scan {sid} still running after {timeout_s} s")


def test_the_api_refuses_what_it_must(server):
    c, key = server.client, {"X-API-Key": KEY}
    assert c.post("/library/scans", json={"folder": "library"}).status_code == 401  # writes need the key
    outside = c.post("/library/scans", json={"folder": "/etc"}, headers=key)
    assert outside.status_code == 422 and "library root" in outside.json()["message"]
    escape = c.post("/library/scans", json={"folder": "library/../../.."}, headers=key)
    assert escape.status_code == 422
    assert c.get("/library/scans/0123456789abcdef", headers=key).status_code == 404
    # Reads need the key too: a scan's results, thumbnails and exports show the server's files.
    for path in ("/library/scans/0123456789abcdef", "/library/scans/0123456789abcdef/photos/1/thumbnail",
                 "/library/scans/0123456789abcdef/export"):  # fmt: skip
        assert c.get(path).status_code == 401, path
    # A manifest under the root is refused: its rows could name any file of the server.
    manifest = server.library.parent / "survey.csv"
    manifest.write_text("image,lat,lon,split\n/etc/hostname,0,0,query\n")
    refused = c.post("/library/scans", json={"folder": "survey.csv"}, headers=key)
    assert refused.status_code == 422 and "not a folder" in refused.json()["message"], refused.json()
    # A scan that fails at once (a folder with no photo) says so instead of staying "running" forever.
    (server.library.parent / "empty").mkdir(exist_ok=True)
    sid = c.post("/library/scans", json={"folder": "empty"}, headers=key).json()["id"]
    state = wait_scan(c, sid)
    assert state["state"] == "failed" and "holds no photos" in state["message"], state
    page = c.get("/library")
    assert page.status_code == 200 and "script-src 'self'" in page.headers["content-security-policy"]
    body = b"{" + b" " * 200_000 + b"}"
    big = c.post("/library/scans", content=body, headers={**key, "Content-Type": "application/json"})
    assert big.status_code == 413  # bodies are bounded


def test_review_on_the_page(browser, server):
    lib, key = server.library, {"X-API-Key": KEY}
    originals = {p.name: sha(p) for p in lib.iterdir()}
    pixels = {p.name: pixel_hash(p) for p in lib.iterdir() if p.name != "notes.jpg"}
    page = open_page(browser, server, "desktop", None)
    page.goto(server.url + "/library")
    page.fill("#api-key", KEY)
    page.fill("#scan-folder", "library")
    page.click("#scan-btn")
    page.wait_for_function("() => /: done, /.test(document.getElementById('lib-status').textContent)", timeout=600_000)
    items = page.locator("#lib-photos li.photo")
    assert items.count() == 21  # 16, 3 from elsewhere, the broken-EXIF photo, the file that is no image
    assert HOSTILE in page.inner_text("#lib-photos") and page.evaluate("window.__xss") is None
    # A file name is text on the page, never HTML; thumbnails load.
    page.wait_for_function("() => [...document.querySelectorAll('#lib-photos img')].some((i) => i.naturalWidth > 0)")
    placed = page.locator("#lib-photos li.photo:has(button.accept:not([disabled]))")
    assert placed.count() >= 3, page.inner_text("#lib-photos")
    names = [placed.nth(n).get_attribute("data-file") for n in range(3)]
    for n in (0, 1):
        page.locator(f'#lib-photos li.photo[data-file="{names[n]}"] button.accept').click()
        page.wait_for_function(
            f"() => document.querySelector('#lib-photos li.photo[data-file=\"{names[n]}\"] .decision')"
        )
    page.locator(f'#lib-photos li.photo[data-file="{names[2]}"] button.reject').click()
    page.wait_for_function(f"() => document.querySelector('#lib-photos li.photo[data-file=\"{names[2]}\"] .decision')")
    assert {p.name: sha(p) for p in lib.iterdir()} == originals  # nothing written without a write
    placed.first.click()  # its pin and candidates on the map
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / "library-desktop.png"), full_page=True)

    page.click("#write-btn")
    page.wait_for_function("() => /wrote 2/.test(document.getElementById('write-result').textContent)")
    scan = server.client.get(page.url.replace(server.url + "/library?scan=", "/library/scans/"), headers=key).json()
    by_file = {p["file"]: p for p in scan["photos"]}
    for f in names[:2]:
        got = subprocess.run(["exiftool", "-n", "-j", "-GPSLatitude", "-GPSLongitude", f + ".xmp"], capture_output=True)
        gps = json.loads(got.stdout)[0]
        want = (by_file[f]["lat"], by_file[f]["lon"])
        assert (gps["GPSLatitude"], gps["GPSLongitude"]) == pytest.approx(want, abs=1e-6)
        assert by_file[f]["decision"] == "accepted" and by_file[f]["written"]["mode"] == "sidecar"
    assert not Path(names[2] + ".xmp").exists() and by_file[names[2]]["decision"] == "rejected"
    assert {p.name: sha(p) for p in lib.iterdir() if p.suffix != ".xmp"} == originals  # byte for byte
    assert {n: pixel_hash(lib / n) for n in pixels} == pixels
    assert not page.errors and page.evaluate("window.__csp") == []

    # A second run skips what is done: every photo keeps its decision, nothing is located again.
    sid = scan["id"]
    again = server.client.post("/library/scans", json={"folder": "library"}, headers=key)
    assert again.status_code == 202 and again.json()["id"] == sid
    state = wait_scan(server.client, sid)
    assert state["state"] == "done" and state["done"] == 0, state
    assert {p["file"]: p["decision"] for p in state["photos"]}[names[0]] == "accepted"

    page.click("#undo-btn")
    page.wait_for_function("() => /undid 2/.test(document.getElementById('write-result').textContent)")
    assert {p.name: sha(p) for p in lib.iterdir()} == originals

    # Moving the pin: a photo with no suggestion (San Francisco) placed by hand on the map.
    item = page.locator("#lib-photos li.photo", has_text="q1.jpg")
    assert item.locator("button.accept").is_disabled()
    item.locator(".name").click()
    page.locator("#lib-map").click(position={"x": 300, "y": 200})
    item.locator("button.move").click()
    page.wait_for_function(
        "() => [...document.querySelectorAll('#lib-photos li.photo')].some("
        "(li) => li.textContent.includes('q1.jpg') && li.querySelector('.decision'))"
    )
    photos = server.client.get(f"/library/scans/{sid}", headers=key).json()["photos"]
    q1 = next(p for p in photos if p["file"].endswith("q1.jpg"))
    assert q1["decision"] == "accepted" and 39.9 < q1["accepted_lat"] < 40.0 and -75.3 < q1["accepted_lon"] < -75.1
    assert not page.errors
    thumb = server.client.get(f"/library/scans/{sid}/photos/{q1['id']}/thumbnail", headers=key)
    assert thumb.status_code == 200 and thumb.headers["cache-control"] == "private, no-store"
    for p in photos:  # the library's decisions as they were: the other tests do not depend on the order
        if p["decision"] is not None:
            server.client.post(f"/library/scans/{sid}/photos/{p['id']}/decision", json={"action": "clear"}, headers=key)


def test_the_api_moves_dry_runs_writes_in_file_exports_and_undoes(server):
    """The rest of the API on the same library (scanned here, or already by the page's test: either order)."""
    c, key = server.client, {"X-API-Key": KEY}
    sid = c.post("/library/scans", json={"folder": str(server.library)}, headers=key).json()["id"]
    scan = wait_scan(c, sid)
    assert scan["state"] == "done", scan
    undecided = [p for p in scan["photos"] if p["kind"] == "located" and p["decision"] is None]
    unplaced = next(p for p in undecided if Path(p["file"]).name.startswith("img_"))
    broken = next(p for p in undecided if Path(p["file"]).name == "broken-exif.jpg")
    c.post(f"/library/scans/{sid}/photos/{broken['id']}/decision", json={"action": "move", "lat": 39.95, "lon": -75.19},
           headers=key)  # fmt: skip
    broken_before = sha(Path(broken["file"]))
    base = f"/library/scans/{sid}/photos/{unplaced['id']}/decision"
    bad = c.post(base, json={"action": "move", "lat": 95, "lon": 0}, headers=key)
    assert bad.status_code == 422 and "lat" in bad.json()["message"]
    assert c.post(base, json={"action": "move", "lat": 39.9512, "lon": -75.1921}).status_code == 401
    moved = c.post(base, json={"action": "move", "lat": 39.9512, "lon": -75.1921}, headers=key).json()
    assert (moved["decision"], moved["accepted_lat"], moved["accepted_lon"]) == ("accepted", 39.9512, -75.1921)
    problem = next(p for p in scan["photos"] if p["kind"] == "problem")
    refused = c.post(f"/library/scans/{sid}/photos/{problem['id']}/decision", json={"action": "accept"}, headers=key)
    assert refused.status_code == 422

    photo = Path(unplaced["file"])
    before, pixels = sha(photo), pixel_hash(photo)
    dry = c.post(f"/library/scans/{sid}/write", json={"in_file": True, "dry_run": True}, headers=key).json()
    assert dry["dry_run"] and unplaced["file"] in [w["file"] for w in dry["written"]] and sha(photo) == before
    done = c.post(f"/library/scans/{sid}/write", json={"in_file": True}, headers=key).json()
    assert unplaced["file"] in [w["target"] for w in done["written"]]
    # A photo whose EXIF is damaged: exiftool cannot write it; said, and the photo left as it was.
    assert [f["file"] for f in done["failed"]] == [broken["file"]], done["failed"]
    assert "broken-exif.jpg" in done["failed"][0]["reason"] and sha(Path(broken["file"])) == broken_before
    got = json.loads(subprocess.run(["exiftool", "-n", "-j", "-GPSLatitude", "-GPSLongitude", str(photo)],
                                    capture_output=True).stdout)[0]  # fmt: skip
    assert (got["GPSLatitude"], got["GPSLongitude"]) == pytest.approx((39.9512, -75.1921), abs=1e-6)
    assert sha(photo) != before and pixel_hash(photo) == pixels  # metadata written, pixels untouched

    geo = c.get(f"/library/scans/{sid}/export", params={"format": "geojson"}, headers=key)
    assert geo.headers["content-type"].startswith("application/geo+json")
    accepted = {Path(f["properties"]["file"]).name: f["geometry"]["coordinates"] for f in geo.json()["features"]}
    assert accepted[photo.name] == [-75.1921, 39.9512]
    everything = c.get(f"/library/scans/{sid}/export", params={"format": "geojson", "all": "true"}, headers=key)
    assert len(everything.json()["features"]) == 21  # every photo without a position, the unreadable one too
    assert "<wpt" in c.get(f"/library/scans/{sid}/export", params={"format": "gpx"}, headers=key).text
    assert c.get(f"/library/scans/{sid}/export", params={"format": "kmz"}, headers=key).status_code == 422

    undone = c.post(f"/library/scans/{sid}/undo", headers=key).json()
    assert str(photo) in undone["restored"] and sha(photo) == before
    for p in (unplaced, broken):  # the decisions of this test taken back: the page's test may come after
        c.post(f"/library/scans/{sid}/photos/{p['id']}/decision", json={"action": "clear"}, headers=key)
