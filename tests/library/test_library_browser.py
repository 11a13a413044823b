"""The Library view in a real browser (Debian's Chromium, as tests/service/test_browser.py drives it), over
a real uvicorn server: the user scans a library folder on the page, accepts two suggestions and rejects
one, and writes: the two have XMP sidecars holding the accepted GPS, the rejected one has nothing, and the
originals are byte for byte (and pixel for pixel) what they were. A second scan skips what is done; undo
on the page restores every file. The API's own answers (a bad folder, a bad decision) are checked too."""

from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path

import pytest

from app.engine.configs import DEFAULT_CONFIG
from app.library.writeback import pixel_hash
from tests.library.conftest import make_library
from tests.service.test_browser import ARGS, CHROMIUM, open_page
from tools.server_process import ServerProcess

pytestmark = pytest.mark.browser
KEY = "library-key"


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs Debian's chromium (make browser)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory, library_models, query_truth):
    root = tmp_path_factory.mktemp("library-root")
    make_library(root / "library", query_truth)
    s = ServerProcess(
        root / "data",
        library_models,
        DEFAULT_CONFIG,
        api_key=KEY,
        extra_env={"GEOLOC_ORT_THREADS": "1", "GEOLOC_LIBRARY_ROOT": str(root)},
    )
    s.wait_ready()
    s.library = root / "library"
    yield s
    s.stop()


def test_the_api_refuses_what_it_must(server):
    c, key = server.client, {"X-API-Key": KEY}
    assert c.post("/library/scans", json={"folder": "library"}).status_code == 401  # writes need the key
    outside = c.post("/library/scans", json={"folder": "/etc"}, headers=key)
    assert outside.status_code == 422 and "library root" in outside.json()["message"]
    escape = c.post("/library/scans", json={"folder": "library/../../.."}, headers=key)
    assert escape.status_code == 422
    assert c.get("/library/scans/0123456789abcdef").status_code == 404
    body = b"{" + b" " * 200_000 + b"}"
    big = c.post("/library/scans", content=body, headers={**key, "Content-Type": "application/json"})
    assert big.status_code == 413  # bodies are bounded


def test_review_on_the_page(browser, server):
    lib = server.library
    originals = {p.name: sha(p) for p in lib.iterdir()}
    pixels = {p.name: pixel_hash(p) for p in lib.iterdir() if p.name != "notes.jpg"}
    page = open_page(browser, server, "desktop", None)
    page.goto(server.url + "/library")
    page.fill("#api-key", KEY)
    page.fill("#scan-folder", "library")
    page.click("#scan-btn")
    page.wait_for_function("() => /: done, /.test(document.getElementById('lib-status').textContent)", timeout=600_000)
    items = page.locator("#lib-photos li.photo")
    assert items.count() == 20  # 16 + 2 from elsewhere + the broken-EXIF photo + the file that is no image
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

    page.click("#write-btn")
    page.wait_for_function("() => /wrote 2/.test(document.getElementById('write-result').textContent)")
    scan = server.client.get(page.url.replace(server.url + "/library?scan=", "/library/scans/")).json()
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
    again = server.client.post("/library/scans", json={"folder": "library"}, headers={"X-API-Key": KEY})
    assert again.status_code == 202 and again.json()["id"] == sid
    for _ in range(600):
        state = server.client.get(f"/library/scans/{sid}").json()
        if state["state"] != "running":
            break
        page.wait_for_timeout(200)
    assert state["state"] == "done" and state["done"] == 0, state
    assert {p["file"]: p["decision"] for p in state["photos"]}[names[0]] == "accepted"

    page.click("#undo-btn")
    page.wait_for_function("() => /undid 2/.test(document.getElementById('write-result').textContent)")
    assert {p.name: sha(p) for p in lib.iterdir()} == originals
