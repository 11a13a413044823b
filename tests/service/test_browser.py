"""The page in a real browser: Debian's headless Chromium driven by Playwright (no browser download)."""

import json
import os
import shutil
from pathlib import Path

import pytest

from app.datasets import read_manifest
from tests.conftest import REPO
from tests.service.conftest import Server, wait_job

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
