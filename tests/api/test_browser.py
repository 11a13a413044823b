"""The page in a real browser: Debian's headless Chromium driven by Playwright (no browser download).

Every page here reaches only the service: map tiles are either answered with a plain generated tile
(the "with tiles" screenshots, deterministic and offline) or refused (the "no tiles" ones), and any other
host is refused. Screenshots go to out/screenshots/ at desktop and phone width.

The page's Content-Security-Policy allows no eval: Playwright evaluates a bare expression given to
wait_for_function with eval, so each predicate here is a function ("() => ...")."""

import io
import json
import re
from pathlib import Path
from urllib.parse import urlparse

import pytest

from app.manifests import read_manifest
from tests.api.conftest import Server, wait_job
from tests.conftest import CHECK_IMAGES, REPO

pytestmark = pytest.mark.browser  # not in `make test-quick`

SHOTS = REPO / "out" / "screenshots"
VIEWPORTS = {"desktop": {"width": 1280, "height": 900}, "phone": {"width": 375, "height": 812}}
TILE_HOST = "tile.openstreetmap.org"
UNRELATED = CHECK_IMAGES / "fox.jpg"  # not a street of the collection: candidates, but no agreement
#: Every Content-Security-Policy violation the page reports, kept in window.__csp (see violations()).
RECORD_VIOLATIONS = """
window.__csp = [];
document.addEventListener("securitypolicyviolation",
  (e) => window.__csp.push(`${e.violatedDirective} ${e.blockedURI}`));
"""


def plain_tile() -> bytes:
    """A 256 px map tile stand-in (light ground, a faint grid): what the page looks like with tiles."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (256, 256), (242, 239, 233))
    draw = ImageDraw.Draw(img)
    for x in range(0, 256, 64):
        draw.line([(x, 0), (x, 255)], fill=(225, 221, 212))
        draw.line([(0, x), (255, x)], fill=(225, 221, 212))
    out = io.BytesIO()
    img.save(out, "PNG")
    return out.getvalue()


@pytest.fixture(scope="module")
def server(tmp_path_factory, fitted_models, mini_manifest):
    """The db photos, plus the crops of the first capture: three references at one spot, so that a query
    with that capture's photo gets a confident estimate and markers 2 and 3 lie exactly under marker 1."""
    s = Server(tmp_path_factory.mktemp("web") / "data", fitted_models, api_key="web-key")
    s.wait_ready()
    db = [r for r in read_manifest(mini_manifest) if r.split == "db"]
    photos = [r for r in db if "/photos/" in str(r.image)]
    crops = [r for r in db if "/crops/" in str(r.image) and r.group == photos[0].group]
    rows = photos + crops
    files = [("image", (r.image.name, r.image.read_bytes(), "image/jpeg")) for r in rows]
    meta = [{"lat": r.lat, "lon": r.lon, "label": r.image.name} for r in rows]
    res = s.client.post(
        "/references", files=files, data={"metadata": json.dumps(meta)}, headers={"X-API-Key": "web-key"}
    )
    wait_job(s.client, res.json()["job_id"])
    s.rows, s.query = rows, photos[0].image
    yield s
    s.stop()


@pytest.fixture(scope="module")
def tile_png():
    return plain_tile()


def open_page(browser, server, viewport: str, tiles: bytes | None):
    """A page on the service; ``tiles`` None refuses every tile (no map background)."""
    page = browser.new_page(viewport=VIEWPORTS[viewport])
    page.errors = []
    page.on("pageerror", lambda e: page.errors.append(str(e)))
    page.add_init_script(RECORD_VIOLATIONS)

    def only_this_service(route):
        host = urlparse(route.request.url).hostname
        if host in ("127.0.0.1", "localhost"):
            route.continue_()
        elif host == TILE_HOST and tiles is not None:
            route.fulfill(status=200, content_type="image/png", body=tiles)
        else:
            route.abort()

    page.route("**/*", only_this_service)
    page.goto(server.url + "/")
    assert page.title().startswith("geoloc")
    return page


def tab_to(page, element_id: str, presses: int = 30) -> None:
    """Press Tab until ``element_id`` has the focus: it is reachable from the keyboard."""
    for _ in range(presses):
        page.keyboard.press("Tab")
        if page.evaluate("document.activeElement && document.activeElement.id") == element_id:
            return
    raise AssertionError(f"#{element_id} is not reachable with Tab")


def choose_with_keyboard(page, photo: Path) -> None:
    """Tab to the file input, open it with Space, pick the photo, Tab to Locate, press Enter."""
    # The listener goes first, so that Playwright intercepts the chooser well before the key press (an
    # expect_file_chooser() opened just before it missed the chooser once in a few runs on a busy machine).
    choosers = []
    page.on("filechooser", lambda chooser: choosers.append(chooser))
    tab_to(page, "locate-file")
    for _ in range(3):
        page.keyboard.press("Space")
        for _ in range(100):
            if choosers:
                break
            page.wait_for_timeout(100)
        if choosers:
            break
    assert choosers, "Space on the focused file input opened no file chooser"
    choosers[0].set_files(str(photo))
    preview = page.locator("#preview")
    preview.wait_for(state="visible")
    page.wait_for_function("() => document.getElementById('preview').naturalWidth > 0")
    assert photo.name in preview.get_attribute("alt")
    tab_to(page, "locate-btn")
    page.keyboard.press("Enter")
    page.wait_for_selector("#answer:not([hidden])", timeout=60_000)


def screenshot(page, name: str) -> None:
    page.wait_for_function("() => [...document.querySelectorAll('#candidates img')].every((i) => i.complete)")
    page.wait_for_timeout(300)  # the map's fit animation
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / name), full_page=True)


def no_horizontal_scroll(page) -> None:
    assert page.evaluate("document.documentElement.scrollWidth") <= page.viewport_size["width"]


def markers(page) -> list[dict]:
    return page.eval_on_selector_all(
        "#map .num-marker",
        """els => els.map(e => {
            const r = e.getBoundingClientRect();
            return {n: e.textContent.trim(), z: Number(e.style.zIndex), best: e.classList.contains('best'),
                    x: r.x, y: r.y, w: r.width, h: r.height};
        })""",
    )


def check_best_marker_on_top(page, count: int) -> None:
    page.locator("#map").scroll_into_view_if_needed()
    ms = markers(page)
    assert len(ms) == count  # markers render whatever the tiles do
    one = next(m for m in ms if m["n"] == "1")
    assert one["best"] and not any(m["best"] for m in ms if m is not one)
    assert all(one["z"] > m["z"] for m in ms if m is not one), ms
    stacked = [
        m for m in ms if m is not one and abs(m["x"] - one["x"]) < one["w"] and abs(m["y"] - one["y"]) < one["h"]
    ]
    assert stacked, "the test collection should put later candidates under marker 1"
    cx, cy = one["x"] + one["w"] / 2, one["y"] + one["h"] / 2
    on_top = page.evaluate(f"document.elementFromPoint({cx}, {cy}).closest('.num-marker').textContent.trim()")
    assert on_top == "1"


@pytest.mark.parametrize("viewport", ["desktop", "phone"])
def test_a_confident_answer_with_the_keyboard(browser, server, tile_png, viewport):
    page = open_page(browser, server, viewport, tile_png)
    choose_with_keyboard(page, server.query)
    assert page.inner_text("#level") == "Likely"
    headline = page.inner_text("#headline")
    assert re.search(r"within \d+ m of -?\d+\.\d{5}, -?\d+\.\d{5}", headline), headline
    explain = page.inner_text("#explain")
    assert re.search(r"\d+ of the \d+ candidates lie within that radius", explain)
    # The mini collection is too small to calibrate: the constant rule's radius, its rate said not calibrated.
    assert "How often the truth lies within that radius is not calibrated on this collection." in explain
    assert re.fullmatch(
        r"Features used: [\d,]+ of the [\d,]+ distinctive points found in your photo\.",
        page.inner_text("#features-used"),
    )
    assert "%" not in page.inner_text("#answer")  # the weight share stays in the closed technical details
    items = page.locator("#candidates li")
    assert items.count() >= 3
    first = items.first.inner_text()
    assert "1. Reference #" in first and server.query.name in first and "best match" in first
    assert "from the estimate" in items.nth(1).inner_text()
    alts = page.locator("#candidates img").evaluate_all("els => els.map(e => e.alt)")
    assert all(a.startswith("Reference ") for a in alts)
    assert "candidates in" in page.inner_text("#locate-status")
    check_best_marker_on_top(page, items.count())
    screenshot(page, f"locate-likely-{viewport}.png")
    if viewport == "phone":
        no_horizontal_scroll(page)
    # The service's own figures stay one keypress away.
    page.focus("#tech-box summary")
    page.keyboard.press("Enter")
    assert re.search(r"Confidence\s+\d+ % of the candidates' weight agrees", page.inner_text("#tech"))

    # The tabs from the keyboard: each keeps its own status line.
    page.focus("#tab-locate")
    page.keyboard.press("ArrowRight")
    page.wait_for_selector("#refs li")
    assert page.evaluate("document.activeElement.id") == "tab-refs"
    assert page.locator("#locate-status").is_hidden() and page.locator("#view-locate").is_hidden()
    assert page.locator("#refs-status").is_visible() or page.inner_text("#refs-status") == ""
    assert "candidates in" not in page.inner_text("#view-refs")
    page.keyboard.press("ArrowLeft")
    assert page.locator("#locate-status").is_visible()
    # The list's Map button (keyboard too) opens the candidate's popup, which names the candidates hidden
    # under it (the crops of the query's capture, at the same position).
    page.focus("#candidates li:nth-child(1) button")
    page.keyboard.press("Space")
    page.wait_for_selector(".leaflet-popup-content")
    popup = page.inner_text(".leaflet-popup-content")
    assert popup.startswith("1. Reference #") and "Also at this spot: " in popup, popup
    assert not page.errors, page.errors


@pytest.mark.parametrize("viewport", ["desktop", "phone"])
def test_an_answer_without_estimate(browser, server, tile_png, viewport, tmp_path):
    page = open_page(browser, server, viewport, tile_png)
    page.set_input_files("#locate-file", str(UNRELATED))
    assert page.locator("#preview").is_visible()
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])", timeout=60_000)
    assert page.inner_text("#level") == "Possible"
    assert page.inner_text("#headline") == "Possible places only: no small disc holds for evidence this strong."
    assert re.search(r"spread over \d", page.inner_text("#explain"))
    assert "from candidate 1" in page.locator("#candidates li").nth(1).inner_text()
    assert page.locator("#map path.leaflet-interactive").count() == 0  # no estimate circle
    # The dashed rectangle (the collection's extent) has its line in the legend.
    assert page.locator("#map path.extent").count() == 1 and page.locator("#legend-extent").is_visible()
    check_markers = markers(page)
    one = next(m for m in check_markers if m["n"] == "1")
    assert all(one["z"] > m["z"] for m in check_markers if m is not one)
    screenshot(page, f"locate-possible-{viewport}.png")
    if viewport == "phone":
        no_horizontal_scroll(page)

    # An error from the API is shown in words, on the locate tab.
    bad = tmp_path / "notes.jpg"
    bad.write_text("not a photo")
    page.set_input_files("#locate-file", str(bad))
    page.click("#locate-btn")
    page.wait_for_selector("#locate-error:not([hidden])")
    assert "not a JPEG" in page.inner_text("#locate-error")
    # Beside the refusal, the caption no longer says the file "can still be located".
    assert "can still be located" not in page.inner_text("#preview-box"), page.inner_text("#preview-box")
    assert not page.errors, page.errors


@pytest.mark.parametrize("viewport", ["desktop", "phone"])
def test_the_page_with_map_tiles_blocked(browser, server, viewport):
    page = open_page(browser, server, viewport, tiles=None)
    page.set_input_files("#locate-file", str(server.query))
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])", timeout=60_000)
    assert page.inner_text("#level") == "Likely"
    page.wait_for_selector("#map-note:not([hidden])")
    assert "tiles" in page.inner_text("#map-note") and "could not load" in page.inner_text("#map-note")
    check_best_marker_on_top(page, page.locator("#candidates li").count())
    assert page.locator("#map path.leaflet-interactive").count() >= 1  # the estimate's circle
    screenshot(page, f"locate-no-tiles-{viewport}.png")
    if viewport == "phone":
        no_horizontal_scroll(page)
    assert not page.errors, page.errors


def test_the_page_without_the_map_library(browser, server):
    """Leaflet missing (a broken install, a blocked file): the answer and the list still work."""
    page = browser.new_page(viewport=VIEWPORTS["phone"])
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.route("**/vendor/leaflet/**", lambda route: route.abort())
    page.goto(server.url + "/")
    assert "did not load" in page.inner_text("#map") and page.locator(".legend").is_hidden()
    page.set_input_files("#locate-file", str(server.query))
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])", timeout=60_000)
    assert page.inner_text("#level") == "Likely" and page.locator("#candidates li").count() >= 3
    assert not errors, errors


def test_no_match(browser, server, tile_png):
    """An answer with no candidate (an empty collection, or a region holding none): said as such. The
    answer is the service's own shape for an empty region, served by the test so the shared collection
    stays as it is."""
    page = open_page(browser, server, "phone", tile_png)
    empty = {
        "candidates": [],
        "estimate": None,
        "reason": "no references in the requested region",
        "mode": "float",
        "config": "hybrid-bin",
        "features": {"extracted": 1000, "kept": 1000},
        "timings_ms": {"total": 12.0},
        "index": {"size": len(server.rows), "version": 1},
    }
    page.route("**/locate", lambda route: route.fulfill(status=200, json=empty))
    page.set_input_files("#locate-file", str(server.query))
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])")
    assert page.inner_text("#level") == "No match"
    assert "no references in the region" in page.inner_text("#headline")
    assert page.locator("#candidates li").count() == 0 and page.locator("#map .num-marker").count() == 0
    assert page.locator("#legend").is_hidden()
    screenshot(page, "locate-no-match-phone.png")
    no_horizontal_scroll(page)
    assert not page.errors, page.errors


def test_markers_a_few_metres_apart_name_each_other(browser, server, tile_png):
    """Two candidates 6 m apart: their markers overlap at the popup's zoom (two markers once hid
    each other unseen), so each popup names the other; one 300 m away is not named."""
    ref = server.client.get("/references?limit=1").json()["items"][0]
    spots = [(0.0, 0.61), (6.0, 0.58), (300.0, 0.55)]  # metres north of the reference, score
    answer = {
        "candidates": [
            {
                "reference_id": ref["id"], "lat": ref["lat"] + m / 111_320, "lon": ref["lon"], "score": s,
                "distance_m": None, "label": None, "captured_at": None, "heading": None, "inliers": None,
                "p_within_25m": None,
            }
            for m, s in spots
        ],
        "estimate": None,
        "reason": "the candidates disagree on the place",
        "reason_code": "ambiguous",
        "mode": "float",
        "config": "hybrid-bin",
        "features": {"extracted": 1200, "kept": 900},
        "timings_ms": {"total": 12.0},
        "index": {"size": len(server.rows), "version": 1},
    }  # fmt: skip
    page = open_page(browser, server, "desktop", tile_png)
    page.route("**/locate", lambda route: route.fulfill(status=200, json=answer))
    page.set_input_files("#locate-file", str(server.query))
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])")
    page.click("#candidates li:nth-child(2) button")
    page.wait_for_selector(".leaflet-popup-content")
    popup = page.inner_text(".leaflet-popup-content")
    assert popup.startswith("2. ") and "Overlapping markers (within 12 m): 1" in popup, popup
    assert "3" not in popup.split("Overlapping markers", 1)[1], popup
    assert not page.errors, page.errors


def test_calibrated_probabilities_in_words(browser, server, tile_png):
    """Where the answer carries each candidate's calibrated ``p_within_25m`` (the application core gives
    it for the first 10), the page says it as a chance; served by the test, in the service's shape."""
    refs = server.client.get("/references?limit=2").json()["items"]
    answer = {
        "candidates": [
            {
                "reference_id": r["id"],
                "lat": r["lat"],
                "lon": r["lon"],
                "score": s,
                "distance_m": None,
                "label": r["label"],
                "captured_at": None,
                "heading": None,
                "inliers": None,
                "p_within_25m": p,
            }
            for r, s, p in zip(refs, (0.61, 0.55), (0.34, 0.12), strict=True)
        ],
        "estimate": None,
        "reason": "ambiguous: the best group holds 40% of the candidates' weight; candidates disagree on the place",
        "mode": "float",
        "config": "hybrid-bin",
        "features": {"extracted": 1200, "kept": 900},
        "timings_ms": {"total": 12.0},
        "index": {"size": len(server.rows), "version": 1},
    }
    page = open_page(browser, server, "desktop", tile_png)
    page.route("**/locate", lambda route: route.fulfill(status=200, json=answer))
    page.set_input_files("#locate-file", str(server.query))
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])")
    assert page.inner_text("#level") == "Possible"
    assert "34 % chance of lying within 25 m" in page.inner_text("#explain")
    assert "12 % chance it is within 25 m" in page.locator("#candidates li").nth(1).inner_text()
    assert page.inner_text("#features-used").startswith("Features used: 900 of the 1,200")
    assert not page.errors, page.errors


def test_a_stated_radius_and_its_rate_in_words(browser, server, tile_png):
    """An answer whose disc the collection calibrated (``radius_rate``) says it in words: "Taken within 35 m
    of ...: 9 in 10 such answers are"; served by the test, in the service's shape (the page's collection is
    too small to calibrate), with a label that is HTML, rendered as text."""
    refs = server.client.get("/references?limit=2").json()["items"]
    label = "<b>bold</b><img src=x onerror=alert(1)>"
    answer = {
        "candidates": [
            {
                "reference_id": r["id"],
                "lat": r["lat"],
                "lon": r["lon"],
                "score": s,
                "distance_m": d,
                "label": label,
                "captured_at": None,
                "heading": None,
                "inliers": None,
                "p_within_25m": p,
            }
            for r, s, p, d in zip(refs, (0.71, 0.69), (0.91, 0.88), (0.0, 12.0), strict=True)
        ],
        "estimate": {"lat": refs[0]["lat"], "lon": refs[0]["lon"], "radius_m": 35.0, "radius_rate": 0.9,
                     "confidence": 0.8},
        "reason": None,
        "reason_code": None,
        "mode": "float",
        "config": "hybrid-bin",
        "features": {"extracted": 1200, "kept": 900},
        "timings_ms": {"total": 12.0},
        "index": {"size": len(server.rows), "version": 1},
    }  # fmt: skip
    page = open_page(browser, server, "desktop", tile_png)
    page.route("**/locate", lambda route: route.fulfill(status=200, json=answer))
    page.set_input_files("#locate-file", str(server.query))
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])")
    assert page.inner_text("#level") == "Likely"
    headline = page.inner_text("#headline")
    assert headline.startswith("Taken within 35 m of ") and headline.endswith(": 9 in 10 such answers are."), headline
    explain = page.inner_text("#explain")
    assert "smallest that held the truth for 9 in 10 of this collection's own answers" in explain, explain
    assert "not calibrated" not in explain
    assert label in page.locator("#candidates li").first.inner_text()  # the label as text
    assert page.locator("#candidates b, #candidates img[src='x']").count() == 0
    assert not page.errors, page.errors


@pytest.mark.parametrize("viewport", ["desktop", "phone"])
def test_no_reference_looks_like_this_photo(browser, server, tile_png, viewport):
    """reason_code no_match (no candidate has a 10 % chance of lying within 25 m): the page says what that
    measures, "No reference looks like this photo", never that the place is absent, and outlines the
    collection's extent on the map. Served by the test in the service's
    shape (the tests' collection is too small to calibrate; tests/api/test_answers.py calibrates one)."""
    refs = server.client.get("/references?limit=3").json()["items"]
    lats, lons = [r["lat"] for r in refs], [r["lon"] for r in refs]
    extent = {"min_lat": min(lats), "min_lon": min(lons), "max_lat": max(lats), "max_lon": max(lons)}
    answer = {
        "candidates": [
            {"reference_id": r["id"], "lat": r["lat"], "lon": r["lon"], "score": s, "distance_m": None,
             "label": r["label"], "captured_at": None, "heading": None, "inliers": None, "p_within_25m": p}
            for r, s, p in zip(refs, (0.58, 0.57, 0.55), (0.03, 0.02, 0.02), strict=True)
        ],
        "estimate": None,
        "reason": "no reference looks like this photo: no candidate has a 10% chance of lying within 25 m of "
        "where it was taken (best 3%)",
        "reason_code": "no_match",
        "mode": "float",
        "config": "hybrid-bin",
        "features": {"extracted": 1000, "kept": 800},
        "timings_ms": {"total": 12.0},
        "index": {"size": len(server.rows), "version": 1, "generation": 0, "extent": extent},
    }  # fmt: skip
    page = open_page(browser, server, viewport, tile_png)
    page.route("**/locate", lambda route: route.fulfill(status=200, json=answer))
    page.set_input_files("#locate-file", str(UNRELATED))
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])")
    assert page.inner_text("#level") == "Unrecognised"
    assert page.inner_text("#headline") == "No reference looks like this photo."
    explain = page.inner_text("#explain")
    assert "not in this collection" not in page.inner_text("#answer") and "not that the place is missing" in explain
    assert "only a 3 % chance" in explain
    assert f"{len(server.rows)} references lie between" in explain and "outlined on the map" in explain
    assert page.locator("#map path.extent").count() == 1  # the collection's extent, drawn
    assert page.locator("#map path.leaflet-interactive").count() == 0  # and no estimate circle
    assert "no_match" in page.text_content("#tech")  # in the closed technical details
    screenshot(page, f"locate-unrecognised-{viewport}.png")
    if viewport == "phone":
        no_horizontal_scroll(page)
    assert not page.errors, page.errors


def test_a_photo_without_features(browser, server, tile_png, tmp_path):
    """A plain blue image, located for real: no candidates, and the page says why in words."""
    import cv2
    import numpy as np

    blue = np.zeros((480, 640, 3), np.uint8)
    blue[:] = (200, 120, 30)
    path = tmp_path / "sky.jpg"
    cv2.imwrite(str(path), blue)
    page = open_page(browser, server, "phone", tile_png)
    page.set_input_files("#locate-file", str(path))
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])", timeout=60_000)
    assert page.inner_text("#level") == "No match"
    assert page.inner_text("#headline") == "This photo has nothing to recognise a place by."
    assert page.inner_text("#answer").count("blank, dark or blurred") == 1, "said once"
    assert page.locator("#candidates li").count() == 0 and page.locator("#map .num-marker").count() == 0
    assert not page.errors, page.errors


def test_references_view_at_phone_width_with_the_keyboard(browser, server):
    page = open_page(browser, server, "phone", None)
    page.focus("#tab-refs")
    page.keyboard.press("Enter")
    page.wait_for_selector("#refs li")
    assert page.locator("#refs li").count() == len(server.rows)
    assert "of " + str(len(server.rows)) in page.inner_text("#refs-count")
    first = page.locator("#refs li").first.inner_text()
    assert "Reference #" in first and ".jpg" in first  # the file name as a detail, not as the title
    # Deleting without the key: refused, and said so.
    page.on("dialog", lambda d: d.accept())
    page.locator("#refs li button").first.click()
    page.wait_for_selector("#refs-error:not([hidden])")
    assert "401" in page.inner_text("#refs-error")
    assert page.locator("#locate-error").is_hidden()
    # With the key (kept for this browser session): deleted.
    page.fill("#api-key", "web-key")
    page.locator("#refs li button").first.click()
    page.wait_for_function(f"() => document.querySelectorAll('#refs li').length == {len(server.rows) - 1}")
    assert page.evaluate("sessionStorage.getItem('geoloc-key')") == "web-key"
    assert "deleted" in page.inner_text("#refs-status")
    no_horizontal_scroll(page)
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


# -- user text is text: labels, file names, notes and messages never run as HTML ----------------------
XSS_KEY = "xss-key"
EXFIL = "/xss-exfil"


def label_payload(via: str) -> str:
    """A label that, parsed as HTML anywhere on the page, sends the API key to the service at /xss-exfil."""
    handler = f"fetch('{EXFIL}?via={via}&k='+sessionStorage.getItem('geoloc-key'))"
    return f"""College Hall"'><img src=x onerror="{handler}">"""


def file_payload(via: str) -> str:
    """The same as a file name: no slash or backslash (the service keeps a path's last part) and no double
    quote (browsers and httpx percent-encode it in a multipart file name)."""
    return f"<img src=x onerror=fetch(String.fromCharCode(47)+'xss-exfil?via={via}')>.jpg"


#: Markup that must stay text; ``.xss-injected`` found in the page means it was parsed.
MARKUP_LABEL = "<b class=xss-injected>bold</b> & <i class=xss-injected>friends</i>"


@pytest.fixture(scope="module")
def xss_server(tmp_path_factory, fitted_models, mini_manifest):
    """A collection whose every label is hostile: the query capture's photo (labelled with the payload),
    one crop labelled by its uploaded file name (a payload too) and one labelled with plain markup. All
    three lie at one spot, so locating the photo lists and draws all three."""
    s = Server(tmp_path_factory.mktemp("xss") / "data", fitted_models, api_key=XSS_KEY)
    s.wait_ready()
    db = [r for r in read_manifest(mini_manifest) if r.split == "db"]
    photos = [r for r in db if "/photos/" in str(r.image)]
    crops = [r for r in db if "/crops/" in str(r.image) and r.group == photos[0].group]
    rows = [photos[0], *crops[:2]]
    names = [rows[0].image.name, file_payload("upload-name"), rows[2].image.name]
    files = [("image", (n, r.image.read_bytes(), "image/jpeg")) for n, r in zip(names, rows, strict=True)]
    meta = [
        {"lat": rows[0].lat, "lon": rows[0].lon, "label": label_payload("label")},
        {"lat": rows[1].lat, "lon": rows[1].lon},  # labelled by the service with its file name
        {"lat": rows[2].lat, "lon": rows[2].lon, "label": MARKUP_LABEL},
    ]
    res = s.client.post("/references", files=files, data={"metadata": json.dumps(meta)}, headers={"X-API-Key": XSS_KEY})
    assert res.status_code == 202, res.text
    assert wait_job(s.client, res.json()["job_id"])["status"] == "done"
    s.labels = [label_payload("label"), file_payload("upload-name"), MARKUP_LABEL]
    s.query, s.other = rows[0].image, photos[1]
    yield s
    s.stop()


def watch_exfil(page) -> list[str]:
    """Every request the page makes to /xss-exfil (a CSP-blocked one is never made)."""
    seen = []
    page.on("request", lambda r: seen.append(r.url) if EXFIL in r.url else None)
    return seen


def check_nothing_ran(page, server, seen: list[str]) -> None:
    """No payload ran (no request to /xss-exfil, in the browser or in the server's access log), none was
    parsed into elements (no on* attribute, no .xss-injected), and the page policy had nothing to block:
    the text is kept as text by the page itself, the policy is only the second line."""
    page.wait_for_timeout(500)  # an onerror handler fires once its broken image has failed
    assert not seen, seen
    assert EXFIL not in Path(server.log.name).read_text()
    parsed = page.evaluate(
        """() => [...document.querySelectorAll('*')].filter((e) =>
            e.classList.contains('xss-injected') || [...e.attributes].some((a) => a.name.startsWith('on'))
        ).map((e) => e.outerHTML)"""
    )
    assert not parsed, parsed
    assert page.evaluate("window.__csp") == []


def test_user_text_stays_text_in_the_locate_view(browser, xss_server, tile_png, tmp_path):
    page = open_page(browser, xss_server, "desktop", tile_png)
    seen = watch_exfil(page)
    page.fill("#api-key", XSS_KEY)  # what a payload would be after
    photo = tmp_path / file_payload("locate-name")
    photo.write_bytes(xss_server.query.read_bytes())
    page.set_input_files("#locate-file", str(photo))
    assert page.get_attribute("#preview", "alt") == f"Your photo: {photo.name}"
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])", timeout=60_000)
    items = page.locator("#candidates li")
    assert items.count() == 3
    listed = page.inner_text("#candidates")
    assert all(t in listed for t in xss_server.labels), listed
    # Every candidate's marker hovered and its popup opened.
    for m in page.locator("#map .num-marker").all():
        m.dispatch_event("mouseover")
        m.dispatch_event("mouseout")
    popups = []
    for i in range(items.count()):
        items.nth(i).locator("button.show").click()
        page.wait_for_function(
            f"() => (document.querySelector('.leaflet-popup-content') || {{}}).textContent?.startsWith('{i + 1}. ')"
        )
        popups.append(page.inner_text(".leaflet-popup-content").split("\n")[0])
    assert {p.split(". ", 1)[1] for p in popups} == set(xss_server.labels), popups
    alts = page.locator("#candidates img").evaluate_all("els => els.map(e => e.alt)")
    assert {a.split(": ", 1)[1] for a in alts} == set(xss_server.labels)
    # A message from the service carrying the payload (its own error shape, served by the test).
    page.route(
        "**/locate",
        lambda route: route.fulfill(status=422, json={"error": "invalid_request", "message": label_payload("error")}),
    )
    page.click("#locate-btn")
    page.wait_for_selector("#locate-error:not([hidden])")
    assert page.inner_text("#locate-error") == f"422: {label_payload('error')}"
    check_nothing_ran(page, xss_server, seen)
    assert not page.errors, page.errors


def test_user_text_stays_text_in_the_references_view(browser, xss_server, tile_png, tmp_path):
    page = open_page(browser, xss_server, "desktop", tile_png)
    seen = watch_exfil(page)
    page.fill("#api-key", XSS_KEY)
    page.click("#tab-refs")
    page.wait_for_selector("#refs li")
    listed = page.inner_text("#refs")
    assert all(t in listed for t in xss_server.labels), listed
    # Every reference's map marker hovered: its tooltip shows the label as it is.
    tips = []
    for path in page.locator("#refs-map path.leaflet-interactive").all():
        path.dispatch_event("mouseover")
        tip = page.locator("#" + path.get_attribute("aria-describedby"))  # Leaflet links a tooltip so
        tip.wait_for(state="visible")
        tips.append(tip.inner_text())
        path.dispatch_event("mouseout")
        page.wait_for_timeout(100)  # the tooltip's own mouseover is where Leaflet's onerror would run
    check_nothing_ran(page, xss_server, seen)
    assert sorted(tips) == sorted(xss_server.labels), tips

    # A new reference named by a hostile file name (no label: the service labels it with the name).
    added = tmp_path / file_payload("add-name")
    added.write_bytes(xss_server.other.image.read_bytes())
    page.set_input_files("#add-file", str(added))
    page.fill("#add-lat", str(xss_server.other.lat))
    page.fill("#add-lon", str(xss_server.other.lon))
    page.click("#add-form button[type=submit]")
    page.wait_for_function("() => document.getElementById('refs-status').textContent === 'Reference indexed.'")
    page.wait_for_function("() => document.querySelectorAll('#refs li').length === 4")
    assert added.name in page.inner_text("#refs")
    # A duplicate with a hostile label: the service's note (quoting both labels) and a failed job's error
    # (served by the test, in the service's shape) are shown as text.
    page.route(
        "**/jobs/*",
        lambda route: route.fulfill(
            json={
                "job_id": "j",
                "status": "failed",
                "items": [{"reference_id": 1, "status": "failed", "error": label_payload("job")}],
            }
        ),
    )
    page.set_input_files("#add-file", str(xss_server.query))
    page.fill("#add-label", label_payload("note"))
    page.click("#add-form button[type=submit]")
    page.wait_for_function("() => document.getElementById('refs-status').textContent.includes('metadata was kept')")
    said = page.inner_text("#refs-status")
    assert said.startswith(f"Encoding failed: {label_payload('job')} image 0 is already stored"), said
    assert '<img src=x onerror="fetch(' in said.split("already stored", 1)[1], said
    # An error message carrying the payload (served by the test).
    page.route(
        "**/references?*",
        lambda route: route.fulfill(status=503, json={"error": "not_ready", "message": label_payload("refs-error")}),
    )
    page.click("#tab-locate")
    page.click("#tab-refs")
    page.wait_for_selector("#refs-error:not([hidden])")
    assert page.inner_text("#refs-error") == f"503: {label_payload('refs-error')}"
    check_nothing_ran(page, xss_server, seen)
    assert not page.errors, page.errors


def test_the_page_policy_contains_a_slip(browser, xss_server, tile_png):
    """Should some later code put user text in as HTML, the page's Content-Security-Policy still stops
    its inline handler: the next slip is contained."""
    page = open_page(browser, xss_server, "desktop", tile_png)
    seen = watch_exfil(page)
    page.evaluate(
        """(payload) => { const d = document.createElement('div'); d.innerHTML = payload; document.body.append(d); }""",
        label_payload("slip"),
    )
    page.wait_for_timeout(1000)  # the broken image fails, its handler is refused (or runs)
    assert not seen, seen
    assert any(v.startswith("script-src") for v in page.evaluate("window.__csp")), page.evaluate("window.__csp")


# -- first use: the region control, the Add flow, /docs at phone width -----------------------------------
def test_a_region_on_the_locate_view(browser, server, tile_png):
    """The API's region (lat, lon, radius_m) from the Locate view: a circle far from every reference gives
    the region's "no match"; a partial one is refused on the page; the photo's own spot finds it again."""
    page = open_page(browser, server, "phone", tile_png)
    page.set_input_files("#locate-file", str(server.query))
    page.click("#region-box summary")
    page.fill("#region-lat", "39.9")
    page.click("#locate-btn")
    page.wait_for_selector("#locate-error:not([hidden])")
    assert "latitude, a longitude and a radius" in page.inner_text("#locate-error")
    page.fill("#region-lon", "-75.3")  # about 10 km from the campus
    page.fill("#region-radius", "300")
    page.click("#locate-btn")
    page.wait_for_selector("#answer:not([hidden])", timeout=60_000)
    assert page.inner_text("#level") == "No match" and "region" in page.inner_text("#headline")
    no_horizontal_scroll(page)
    screenshot(page, "locate-region-phone.png")
    first = server.rows[0]
    page.fill("#region-lat", str(first.lat))
    page.fill("#region-lon", str(first.lon))
    page.click("#locate-btn")
    page.wait_for_selector("#candidates li", timeout=60_000)
    assert page.inner_text("#level") in ("Likely", "Possible")
    assert not page.errors, page.errors


def test_add_shows_the_new_reference_and_clears_the_form(browser, server, tile_png, mini_manifest):
    """More references than a page holds (20): the one added from the page used to land on page 2 while the
    file stayed chosen. Now the form is emptied, the reference is shown above the list, and the list moves
    to the page that holds it, marked there."""
    rows = read_manifest(mini_manifest)
    new, *others = [r for r in rows if r.split == "query"]
    extra = [r for r in rows if r.split == "train"] + others  # 17 photos and crops not stored yet
    files = [("image", (r.image.name, r.image.read_bytes(), "image/jpeg")) for r in extra]
    meta = [{"lat": r.lat, "lon": r.lon} for r in extra]
    res = server.client.post(
        "/references", files=files, data={"metadata": json.dumps(meta)}, headers={"X-API-Key": "web-key"}
    )
    wait_job(server.client, res.json()["job_id"])
    total = server.client.get("/references").json()["total"]
    assert total > 20, total

    page = open_page(browser, server, "phone", tile_png)
    page.fill("#api-key", "web-key")
    page.click("#tab-refs")
    page.wait_for_selector("#refs li")
    page.set_input_files("#add-file", str(new.image))
    page.fill("#add-lat", str(new.lat))
    page.fill("#add-lon", str(new.lon))
    page.fill("#add-label", "Added from the page")
    page.click("#add-form button[type=submit]")
    page.wait_for_selector("#refs-added:not([hidden])", timeout=90_000)
    added = page.locator("#refs-added li")
    assert "Added from the page" in added.inner_text() and "Just added" in page.inner_text("#refs-added-title")
    new_id = added.get_attribute("data-id")
    page.wait_for_selector(f'#refs li.added[data-id="{new_id}"]')  # listed, on the page it falls on
    # The list moved to the last page by id (before=the largest id), which ends with the new reference.
    assert page.inner_text("#refs-count").endswith(f"–#{new_id} (by id), of {total + 1}")
    assert page.locator("#next").is_disabled() and not page.locator("#prev").is_disabled()
    assert 21 <= total + 1 <= 40, total  # two pages of 20: the last one full, the first one the rest
    listed: list[str] = []
    page.on("request", lambda r: listed.append(r.url) if "/references?" in r.url else None)
    page.click("#prev")  # before= the first id shown: the lowest ids, the first page
    page.wait_for_function("() => document.getElementById('prev').disabled")
    first_ids = [int(i) for i in page.locator("#refs li").evaluate_all("els => els.map(e => e.dataset.id)")]
    assert first_ids == sorted(first_ids) and len(first_ids) == total + 1 - 20
    assert page.inner_text("#refs-count").startswith(f"References #{first_ids[0]}–")
    assert page.inner_text("#refs-count").endswith(f"of {total + 1}")  # the count kept, not read again
    assert listed and not any("total=true" in u for u in listed), listed
    assert not page.locator("#next").is_disabled()
    # Every reference of the page shown deleted (the last from the page itself): the emptied page steps to
    # the next one instead of leaving both buttons disabled on nothing. This empties the module's server of
    # its first references (server.rows[0] among them): keep this test after every test that locates there.
    for ref_id in first_ids[:-1]:
        assert server.client.delete(f"/references/{ref_id}", headers={"X-API-Key": "web-key"}).status_code == 200
    page.once("dialog", lambda d: d.accept())
    page.click(f'#refs li[data-id="{first_ids[-1]}"] button')
    page.wait_for_function(
        "(gone) => !document.querySelector(`#refs li[data-id='${gone}']`)"
        " && document.querySelectorAll('#refs li').length",
        arg=str(first_ids[-1]),
    )
    assert page.inner_text("#refs-count").endswith(f"of {total + 1 - len(first_ids)}")
    assert page.locator("#prev").is_disabled()
    for ref_id in first_ids:  # the rest of the test reads the form, not the list
        assert server.client.get(f"/references/{ref_id}").status_code == 404
    form = page.evaluate(
        "() => [document.getElementById('add-file').files.length, ...['add-lat', 'add-lon', 'add-label']"
        ".map((id) => document.getElementById(id).value)]"
    )
    assert form == [0, "", "", ""], form
    assert "indexed" in page.inner_text("#refs-status").lower() or "indexed" in added.inner_text()
    no_horizontal_scroll(page)
    page.screenshot(path=str(SHOTS / "references-added-phone.png"), full_page=True)
    assert not page.errors, page.errors


def test_api_docs_fit_a_phone(browser, server):
    """The API description's error table used to widen /docs past 375 px: it now scrolls inside itself."""
    page = browser.new_page(viewport=VIEWPORTS["phone"])
    page.route("**/*", lambda r: r.continue_() if urlparse(r.request.url).hostname == "127.0.0.1" else r.abort())
    page.goto(server.url + "/docs")
    page.locator('.opblock-summary-path[data-path="/locate"]').wait_for(state="visible", timeout=30_000)
    assert page.locator(".info table").count() >= 1
    assert page.evaluate("getComputedStyle(document.querySelector('.info table')).overflowX") == "auto"
    no_horizontal_scroll(page)
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / "docs-phone.png"), full_page=True)
