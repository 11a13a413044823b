"""The page in a real browser: Debian's headless Chromium driven by Playwright (no browser download)."""

import json
import os
import shutil
from pathlib import Path
from urllib.parse import urlparse

import pytest

from app.datasets import read_manifest
from tests.conftest import REPO
from tests.service.conftest import Server, wait_job

pytestmark = pytest.mark.browser  # not in `make test-quick`

CHROMIUM = os.environ.get("GEOLOC_CHROMIUM", "/usr/bin/chromium")
SHOTS = REPO / "out" / "screenshots"
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
    "--disable-quic",
]


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
def server(tmp_path_factory, fitted_models, mini_manifest):
    s = Server(tmp_path_factory.mktemp("web") / "data", fitted_models, api_key="web-key")
    s.wait_ready()
    rows = [r for r in read_manifest(mini_manifest) if r.split == "db" and "/photos/" in str(r.image)]
    files = [("image", (r.image.name, r.image.read_bytes(), "image/jpeg")) for r in rows]
    meta = [{"lat": r.lat, "lon": r.lon, "label": r.image.name} for r in rows]
    res = s.client.post(
        "/references", files=files, data={"metadata": json.dumps(meta)}, headers={"X-API-Key": "web-key"}
    )
    wait_job(s.client, res.json()["job_id"])
    s.rows = rows
    yield s
    s.stop()


def test_locate_a_photo_in_the_page(browser, server, tmp_path):
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/")
    assert page.title().startswith("geoloc")
    query = server.rows[0].image
    page.set_input_files("#locate-file", str(query))
    page.click("#locate-btn")
    page.wait_for_selector("#candidates li", timeout=60_000)
    items = page.locator("#candidates li")
    assert items.count() >= 3
    assert query.name in items.first.inner_text()
    assert page.locator(".num-marker").count() == items.count()  # markers render even without map tiles
    alts = [a for a in page.locator("#candidates img").evaluate_all("els => els.map(e => e.alt)")]
    assert all(a.startswith("Reference ") for a in alts)
    assert "candidates in" in page.inner_text("#status")
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / "locate.png"), full_page=True)
    shutil.copy(SHOTS / "locate.png", tmp_path / "locate.png")

    # An error from the API is shown in words.
    bad = tmp_path / "notes.jpg"
    bad.write_text("not a photo")
    page.set_input_files("#locate-file", str(bad))
    page.click("#locate-btn")
    page.wait_for_selector("#error:not([hidden])")
    assert "not a JPEG" in page.inner_text("#error")
    assert not errors, errors


def test_references_view_at_phone_width_with_the_keyboard(browser, server):
    page = browser.new_page(viewport={"width": 390, "height": 844})
    page.goto(server.url + "/")
    page.focus("#tab-refs")
    page.keyboard.press("Enter")
    page.wait_for_selector("#refs li")
    assert page.locator("#refs li").count() == len(server.rows)
    assert "of " + str(len(server.rows)) in page.inner_text("#refs-count")
    # Deleting without the key: refused, and said so.
    page.on("dialog", lambda d: d.accept())
    page.locator("#refs li button").first.click()
    page.wait_for_selector("#error:not([hidden])")
    assert "401" in page.inner_text("#error")
    # With the key (kept for this browser session): deleted.
    page.fill("#api-key", "web-key")
    page.locator("#refs li button").first.click()
    page.wait_for_function(f"document.querySelectorAll('#refs li').length == {len(server.rows) - 1}")
    assert page.evaluate("sessionStorage.getItem('geoloc-key')") == "web-key"
    width = page.evaluate("document.documentElement.scrollWidth")
    assert width <= 400  # no horizontal scrolling at phone width
    page.screenshot(path=str(SHOTS / "references-phone.png"), full_page=True)


def test_api_docs_render_with_no_network_beyond_the_service(browser, server):
    """/docs is Swagger UI from the app's own files: with every other host blocked it still shows the
    operations, and it never even tries another host."""
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    blocked = []

    def only_this_service(route):
        host = urlparse(route.request.url).hostname
        if host in ("127.0.0.1", "localhost"):
            route.continue_()
        else:
            blocked.append(route.request.url)
            route.abort()

    page.route("**/*", only_this_service)
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/docs")
    locate = page.locator('.opblock-summary-path[data-path="/locate"]')
    locate.wait_for(state="visible", timeout=30_000)
    assert page.locator(".opblock").count() >= 9  # every operation, not just the first
    locate.click()  # the operation opens, with its parameters and its documented errors
    page.wait_for_selector(".opblock.is-open .parameters-container, .opblock.is-open .opblock-section")
    assert "unreadable_image" in page.locator(".opblock.is-open").inner_text()
    assert not blocked, blocked
    assert not errors, errors
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / "docs-offline.png"))
    icon = page.request.get(server.url + "/favicon.ico")
    assert icon.status == 200 and icon.headers["content-type"] == "image/x-icon" and icon.body()[:4] == b"\0\0\1\0"
    redoc = page.request.get(server.url + "/redoc")  # turned off rather than loaded from a CDN
    assert redoc.status == 404 and redoc.json()["error"] == "not_found"
