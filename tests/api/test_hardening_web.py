"""The page's own defences and the thumbnails' privacy, against a real server.

The page is tried with hostile text in a real browser in test_browser.py; here are its headers, the
static rules that keep user text out of HTML (index.html has nothing inline the policy would have to
allow; app.js never parses strings as HTML), and the thumbnail, which must carry pixels only."""

from __future__ import annotations

import io
import json
import struct
from html.parser import HTMLParser

import pytest
from PIL import Image, ImageCms

from app.api.app import WEB_DIR
from tests.api.conftest import Server, wait_job
from tests.conftest import PENN, penn_photo

SECRET = b"home address: 12 Secret Lane, Philadelphia"


@pytest.fixture(scope="module")
def server(tmp_path_factory, fitted_models):
    s = Server(tmp_path_factory.mktemp("hardening-web") / "data", fitted_models)
    s.wait_ready()
    yield s
    s.stop()


# -- the page's headers -------------------------------------------------------------------------------------
def directives(policy: str) -> dict[str, list[str]]:
    out = {}
    for part in policy.split(";"):
        name, *values = part.split()
        out[name] = values
    return out


def test_the_page_has_a_content_security_policy(server):
    """No inline script, no eval, no plugin, no <base> rewrite, never framed: an injected handler would
    not run. Tiles (the only other host) are images only."""
    res = server.client.get("/")
    assert res.status_code == 200 and "text/html" in res.headers["content-type"]
    policy = directives(res.headers["content-security-policy"])
    assert policy["default-src"] == ["'self'"]
    assert policy["script-src"] == ["'self'"]  # no 'unsafe-inline', no 'unsafe-eval', no other host
    assert policy["object-src"] == ["'none'"] and policy["base-uri"] == ["'none'"]
    assert policy["frame-ancestors"] == ["'none'"]
    assert "https://tile.openstreetmap.org" in policy["img-src"]
    assert not any("unsafe" in v for values in policy.values() for v in values), policy
    assert res.headers["x-content-type-options"] == "nosniff"
    assert res.headers["x-frame-options"] == "DENY"


def test_the_docs_are_never_framed(server):
    """/docs runs Swagger UI's inline start-up script, so it does not get the page's script policy (the
    browser test shows it still renders); it is still never framed and never sniffed."""
    res = server.client.get("/docs")
    assert res.status_code == 200
    assert directives(res.headers["content-security-policy"]) == {"frame-ancestors": ["'none'"]}
    assert res.headers["x-content-type-options"] == "nosniff" and res.headers["x-frame-options"] == "DENY"


class _Inline(HTMLParser):
    """Collects what a script policy without 'unsafe-inline' would block or what could carry script."""

    def __init__(self):
        super().__init__()
        self.found: list[str] = []

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name.startswith("on") or name == "style" or (value or "").strip().lower().startswith("javascript:"):
                self.found.append(f"<{tag} {name}={value!r}>")
        if tag == "script" and not dict(attrs).get("src"):
            self.found.append("<script> without src")
        if tag == "style":
            self.found.append("<style>")


def test_index_html_has_nothing_inline():
    parser = _Inline()
    parser.feed((WEB_DIR / "index.html").read_text())
    assert parser.found == []


def test_app_js_never_parses_strings_as_html():
    """User and server text is put in with textContent and DOM nodes; a string of HTML is how the map
    tooltip ran a label (escaping first, then innerHTML, is the habit this replaces)."""
    js = (WEB_DIR / "app.js").read_text()
    for sink in ("innerHTML", "outerHTML", "insertAdjacentHTML", "document.write", "escapeHtml"):
        assert sink not in js, sink


# -- thumbnails: pixels only -----------------------------------------------------------------------------------
def segment(marker: int, payload: bytes) -> bytes:
    return struct.pack(">BBH", 0xFF, marker, len(payload) + 2) + payload


def with_private_segments(jpeg: bytes) -> bytes:
    """The photo as a phone or an editor may leave it: a comment (COM), XMP, an ICC profile and IPTC
    (Photoshop APP13), each carrying the secret, spliced in after SOI; its EXIF stays."""
    assert jpeg[:2] == b"\xff\xd8"
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    xmp = b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:Description>' + SECRET + b"</rdf:Description></x:xmpmeta>"
    extra = (
        segment(0xFE, SECRET)
        + segment(0xE1, b"http://ns.adobe.com/xap/1.0/\0" + xmp)
        + segment(0xE2, b"ICC_PROFILE\0\x01\x01" + srgb)
        + segment(0xED, b"Photoshop 3.0\x008BIM\x04\x04\0\0" + struct.pack(">I", len(SECRET) + 5) + b"\x1c\x02\x78"
                  + struct.pack(">H", len(SECRET)) + SECRET + b"\0")
    )  # fmt: skip
    return jpeg[:2] + extra + jpeg[2:]


def markers_before_scan(jpeg: bytes) -> list[int]:
    """The JPEG's segment markers up to the image data (SOS)."""
    out, at = [], 2
    while True:
        assert jpeg[at] == 0xFF, at
        marker = jpeg[at + 1]
        if marker == 0xDA:
            return out
        out.append(marker)
        at += 2 + struct.unpack(">H", jpeg[at + 2 : at + 4])[0]


def test_a_thumbnail_carries_pixels_only(server):
    photo = penn_photo("img_00000.jpg")
    assert photo.parent.parent == PENN
    upload = with_private_segments(photo.read_bytes())
    with Image.open(io.BytesIO(upload)) as im:  # the upload really carries all of it
        assert SECRET in im.info["comment"] and SECRET in im.info["xmp"] and "icc_profile" in im.info
        assert "exif" in im.info
    res = server.client.post(
        "/references",
        files=[("image", ("private.jpg", upload, "image/jpeg"))],
        data={"metadata": json.dumps([{"lat": 39.9516483, "lon": -75.1922449, "label": "College Hall"}])},
    )
    assert res.status_code == 202, res.text
    assert wait_job(server.client, res.json()["job_id"])["status"] == "done"
    ref_id = res.json()["reference_ids"][0]

    thumb = server.client.get(f"/references/{ref_id}/image")
    assert thumb.status_code == 200 and thumb.headers["content-type"] == "image/jpeg"
    body = thumb.content
    assert SECRET not in body and b"Secret Lane" not in body
    with Image.open(io.BytesIO(body)) as im:
        assert max(im.size) == 320 and im.mode == "RGB"
        for key in ("comment", "exif", "xmp", "icc_profile", "photoshop", "adobe"):
            assert key not in im.info, key
    # Only what a plain JPEG encoder writes: JFIF (APP0), tables, frame; no APP1..APP15, no COM.
    kept = markers_before_scan(body)
    assert [m for m in kept if 0xE1 <= m <= 0xEF or m == 0xFE] == [], [hex(m) for m in kept]
    assert kept[0] == 0xE0 and body[6:11] == b"JFIF\0"
