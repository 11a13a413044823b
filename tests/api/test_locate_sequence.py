"""POST /locate/sequence through a real uvicorn server: a held-out penn walk located as one path, and bad
input refused with a clear 4xx JSON body (nothing located, nothing stored); the page sends several photos
chosen at once there and draws the path (Chromium, as tests/api/test_browser.py drives it)."""

from __future__ import annotations

import json
import re

import pytest

from tests.api.conftest import Server
from tests.conftest import PENN
from tests.walks import CONFIG

ELSEWHERE = sorted((PENN.parent / "sf-streetview-toy").glob("*/*.jpg"))  # the 22 images: San Francisco


@pytest.fixture(scope="module")
def server(walk_collection):
    models, data, _ = walk_collection
    s = Server(data, models, extra_env={"GEOLOC_MAX_SEQUENCE_IMAGES": "10", "GEOLOC_MAX_UPLOAD_BYTES": "3000000"})
    assert s.config == CONFIG
    s.wait_ready()
    yield s
    s.stop()


def _files(paths):
    return [("image", (p.name, p.read_bytes(), "image/jpeg")) for p in paths]


def _count(server) -> int:
    return server.client.get("/references", params={"limit": 1}).json()["total"]


def test_a_walk_is_located_as_one_path(server, walk_collection):
    _, _, walk = walk_collection
    r = server.client.post("/locate/sequence", files=_files(walk), data={"top_k": 3}, timeout=300)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["times_from"] == "exif"  # the penn photos carry DateTimeOriginal
    assert out["note"] is None  # the collection is calibrated on itself: the sequence informs the answers
    assert len(out["answers"]) == len(out["path"]) == len(walk)
    for a in out["answers"]:
        assert a["rests_on"] in ("pixels", "sequence")
        assert len(a["candidates"]) <= 3
        assert a["config"] == CONFIG
        assert (a["estimate"] is None) == (a["reason_code"] is not None)
        if a["rests_on"] == "sequence":
            assert a["estimate"] is not None and a["sequence_p"] is not None
            assert a["estimate"]["radius_rate"] is None  # measured on single photos: not claimed here
    # The same photos one by one: each single answer is what the sequence's "pixels" answers say.
    for photo, a in zip(walk, out["answers"], strict=True):
        if a["rests_on"] != "pixels" or a["estimate"] is None:
            continue
        alone = server.client.post("/locate", files=_files([photo]), data={"top_k": 3}).json()
        assert alone["estimate"] == a["estimate"]


def test_photos_in_any_order_are_located_in_the_order_taken(server, walk_collection):
    """order=taken: the walk sent shuffled is located in its EXIF time order, as it is sent in order, and
    ``images`` names each answer's photo among those sent; without it, the same shuffle is refused."""
    _, _, walk = walk_collection
    assert len(walk) == 8
    shuffled = [3, 0, 5, 1, 7, 2, 6, 4]
    sent = [walk[n] for n in shuffled]
    in_order = server.client.post("/locate/sequence", files=_files(walk), timeout=300).json()
    assert in_order["images"] == list(range(len(walk)))
    r = server.client.post("/locate/sequence", files=_files(sent), data={"order": "taken"}, timeout=300)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["times_from"] == "exif"
    assert [shuffled[n] for n in out["images"]] == list(range(len(walk)))
    assert out["path"] == in_order["path"]
    for a, b in zip(out["answers"], in_order["answers"], strict=True):
        assert (a["estimate"], a["rests_on"], a["candidates"]) == (b["estimate"], b["rests_on"], b["candidates"])
    refused = server.client.post("/locate/sequence", files=_files(sent), timeout=300)
    assert refused.status_code == 422 and "go backwards" in refused.json()["message"]


def test_given_times_in_any_order_and_broken_photos_named_as_sent(server, walk_collection):
    """order=taken reads given times too, unchecked; photos that cannot be located are named by their position
    as sent, in that order, whatever the order they were located in."""
    from app.usecases.sequence_inputs import exif_time

    _, _, walk = walk_collection
    times = ["2024-09-23T16:12:00-04:00", "2024-09-23T16:10:00-04:00"]
    r = server.client.post(
        "/locate/sequence", files=_files(walk[:2]), data={"taken_at": times, "order": "taken"}, timeout=300
    )
    assert r.status_code == 200, r.text
    assert r.json()["images"] == [1, 0] and r.json()["times_from"] == "given"

    def cut(photo):  # its EXIF time still readable, its pixels not
        data = photo.read_bytes()[: photo.stat().st_size // 3]
        assert exif_time(data) is not None
        return data

    # Sent: the walk's 6th photo cut, its 1st whole, its 4th cut; located in time order: 1st, 4th, 6th.
    files = [
        ("image", ("late.jpg", cut(walk[5]), "image/jpeg")),
        ("image", ("first.jpg", walk[0].read_bytes(), "image/jpeg")),
        ("image", ("middle.jpg", cut(walk[3]), "image/jpeg")),
    ]
    r = server.client.post("/locate/sequence", files=files, data={"order": "taken"}, timeout=300)
    assert r.status_code == 400, r.text
    message = r.json()["message"]
    assert "2 of the 3 images" in message and "image 1:" not in message
    assert 0 <= message.index("image 0:") < message.index("image 2:"), message


def test_given_times_and_bounds_are_read(server, walk_collection):
    _, _, walk = walk_collection
    times = [f"2024-09-23T16:{10 + n:02d}:00-04:00" for n in range(3)]
    data = {"taken_at": times, "max_speed_mps": "1.5", "max_step_m": "80"}
    r = server.client.post("/locate/sequence", files=_files(walk[:3]), data=data, timeout=300)
    assert r.status_code == 200, r.text
    assert r.json()["times_from"] == "given"


def test_photos_from_elsewhere_get_no_estimate(server):
    r = server.client.post("/locate/sequence", files=_files(ELSEWHERE[:10]), timeout=300)
    assert r.status_code == 200, r.text
    assert all(a["estimate"] is None for a in r.json()["answers"])


@pytest.mark.parametrize(
    "n, data, status, words",
    [
        (1, {}, 422, "at least 2 images"),
        (11, {}, 422, "at most 10 images"),
        (2, {"taken_at": ["yesterday", "2024-09-23T16:10:00"]}, 422, "taken_at of image 0"),
        (2, {"taken_at": ["2024-09-23T16:10:00"]}, 422, "one per image"),
        (2, {"taken_at": ["2024-09-23T16:10:00", "2024-09-23T16:09:00"]}, 422, "go backwards"),
        (2, {"max_speed_mps": "-1"}, 422, "max_speed_mps"),
        (2, {"order": "by name"}, 422, "order"),
    ],
)
def test_bad_sequences_are_refused(server, n, data, status, words):
    before = _count(server)
    photo = PENN / "photos" / "img_00001.jpg"
    r = server.client.post("/locate/sequence", files=_files([photo] * n), data=data)
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/json")
    assert words in r.text
    assert _count(server) == before


def test_every_broken_image_is_named(server):
    good = (PENN / "photos" / "img_00001.jpg").read_bytes()
    files = [
        ("image", ("a.jpg", good, "image/jpeg")),
        ("image", ("notes.txt", b"hello, I am text", "image/jpeg")),
        ("image", ("b.jpg", good, "image/jpeg")),
        ("image", ("cut.jpg", good[: len(good) // 3], "image/jpeg")),
    ]
    r = server.client.post("/locate/sequence", files=files, timeout=300)
    assert r.status_code == 400, r.text
    body = r.json()
    assert body["error"] == "unreadable_image"
    assert "2 of the 4 images" in body["message"]
    assert "image 1:" in body["message"] and "image 3:" in body["message"]
    assert "image 0:" not in body["message"]


def test_a_body_over_the_bound_is_refused_before_it_is_read(server):
    # 10 images x 3 MB + the form's overhead: a declared length beyond it is refused unread.
    big = b"\xff" * (1024 * 1024)
    files = [("image", (f"{n}.jpg", big, "image/jpeg")) for n in range(40)]
    r = server.client.post("/locate/sequence", files=files)
    assert r.status_code == 413, r.text
    assert r.json()["error"] == "too_large"
    assert str(10 * 3_000_000 + 1024 * 1024) in r.json()["message"]


@pytest.mark.browser
@pytest.mark.parametrize("viewport, photos", [("desktop", "collection"), ("phone", "walk")])
def test_the_page_locates_several_photos_as_one_path(
    browser, server, walk_collection, penn_index, tmp_path, viewport, photos
):
    """Several photos chosen on the page go to /locate/sequence, located in the order they were taken: the
    summary, each photo's answer in words (what it rests on), a marker per placed photo and the path on the
    map, as the API answers the same photos. ``collection``: six captures of one phone the collection holds
    (placed, a path drawn), named in the order taken; ``walk``: the held-out walk (the collection's extent
    outlined where nothing is placed), named against it (the page lists them by time, not by name). One file
    name is HTML: it stays text."""
    from tests.api.test_browser import markers, no_horizontal_scroll, open_page, plain_tile, screenshot

    _, _, walk = walk_collection
    if photos == "collection":
        walk = [PENN / r["photo"] for r in [r for r in penn_index if r["photo"]][21:27]]
    names = (
        [p.name for p in walk] if photos == "collection" else [f"photo {len(walk) - n}.jpg" for n in range(len(walk))]
    )
    names[-1] = "walk <img src=x onerror=alert(1)>.jpg"  # the walk's last photo in time
    chosen = []
    for p, name in zip(walk, names, strict=True):
        (tmp_path / name).write_bytes(p.read_bytes())
        chosen.append(str(tmp_path / name))
    expected = server.client.post("/locate/sequence", files=_files(walk), data={"top_k": 10}, timeout=300).json()

    page = open_page(browser, server, viewport, plain_tile())
    page.set_input_files("#locate-file", list(reversed(chosen)))  # the page orders them by name
    assert f"{len(walk)} photos: press Locate" in page.inner_text("#locate-status")
    page.click("#locate-btn")
    page.wait_for_selector("#sequence:not([hidden]), #locate-error:not([hidden])", timeout=300_000)
    assert page.locator("#locate-error").is_hidden(), page.inner_text("#locate-error")
    assert not page.errors, page.errors

    placed = sum(a["estimate"] is not None for a in expected["answers"])
    summary = page.inner_text("#sequence-summary")
    assert summary.startswith(f"{len(walk)} photos located as one path, in the order of the times they were taken")
    assert f": {placed} placed" in summary and f"{len(walk) - placed} without an estimate" in summary, summary
    assert page.locator("#sequence-note").is_hidden()  # a calibrated collection: the path informs the answers
    items = page.locator("#sequence-answers li")
    assert items.count() == len(walk)
    for n, (a, name) in enumerate(zip(expected["answers"], names, strict=True)):
        text = items.nth(n).inner_text()
        assert text.startswith(f"Photo {n + 1}") and name in text, text
        assert ("Likely" in text) == (a["estimate"] is not None), text
        assert ("Placed by the path through the photos around it" in text) == (a["rests_on"] == "sequence"), text
        if a["estimate"] is not None and a["rests_on"] == "pixels":
            assert "From this photo alone." in text
    assert page.locator("#sequence-answers img[src='x']").count() == 0  # the HTML file name stayed text

    shown = [
        n for n, (a, q) in enumerate(zip(expected["answers"], expected["path"], strict=True))
        if a["estimate"] is not None or q["in_collection"]
    ]  # fmt: skip
    assert sorted(int(m["n"]) for m in markers(page)) == [n + 1 for n in shown]
    runs, run = 0, 0
    for q in expected["path"]:
        run = run + 1 if q["in_collection"] else 0
        runs += run == 2
    assert page.locator("#map path.sequence-path").count() == runs
    assert page.locator("#legend-path").is_visible() == (runs > 0)
    assert page.locator("#legend-best").is_hidden()
    assert page.locator("#map path.extent").count() == (0 if shown else 1)
    if photos == "collection":  # what the map draws is exercised: photos placed, a path through them
        assert placed >= 2 and runs >= 1, expected["path"]
        page.focus("#sequence-answers li:nth-child(1) button")
        page.keyboard.press("Enter")
        page.wait_for_selector(".leaflet-popup-content")
        assert page.inner_text(".leaflet-popup-content").startswith("Photo 1")
        # An answer that rests on the sequence, said so (these photos are each confident alone: the service's
        # own answer, with its second photo's marked as the path's).
        by_path = json.loads(json.dumps(expected))
        by_path["answers"][1]["rests_on"] = "sequence"
        page.route("**/locate/sequence", lambda route: route.fulfill(status=200, json=by_path))
        page.click("#locate-btn")
        page.wait_for_function("() => document.querySelector('#sequence-summary').textContent.includes('by the path')")
        assert "(1 by the path through the photos around them)" in page.inner_text("#sequence-summary")
        assert "Placed by the path through the photos around it" in items.nth(1).inner_text()
        # A refusal names the photos by their file names (the service numbers them in the order sent).
        refusal = {"error": "unreadable_image", "message": "1 of the 6 images cannot be located (image 2: not a JPEG)"}
        page.unroute("**/locate/sequence")
        page.route("**/locate/sequence", lambda route: route.fulfill(status=400, json=refusal))
        page.click("#locate-btn")
        page.wait_for_selector("#locate-error:not([hidden])")
        sent = sorted(names, key=lambda n: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", n)])
        assert f"({sent[2]}: not a JPEG)" in page.inner_text("#locate-error")
    screenshot(page, f"locate-sequence-{photos}-{viewport}.png")
    if viewport == "phone":
        no_horizontal_scroll(page)
    assert not page.errors, page.errors
    assert page.evaluate("() => window.__csp") == []
