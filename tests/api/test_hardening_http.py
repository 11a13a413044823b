"""Hardening of the HTTP layer, on a real server.

- A body is refused (401 before it is read, 413 as soon as it is too long) before 64 MB of a 300 MB body
  are read, whatever the client says about its length: counted on the client, by how many bytes the
  server let it send before it answered.
- ``metadata`` is validated like the JSON routes: a number too large for a float, a deep nesting, a
  boolean position, an over-long label, an object as capture time or a control character are 422s that
  keep the keep-alive connection, never 500s; the form, ``metadata``, PATCH and file names agree.
- A 503 names no absolute server path."""

from __future__ import annotations

import json
import re

import httpx
import pytest

from tests.api.conftest import Server, wait_job
from tests.conftest import PENN

KEY = "hardening-key"
MB = 1024 * 1024
TOTAL = 300 * MB  # an oversized body, far past READ_AT_MOST
READ_AT_MOST = 64 * MB
CROP = (PENN / "crops" / "img_00001_0.jpg").read_bytes()
BOUNDARY = "hardening"
PREAMBLE = (
    f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="image"; filename="big.jpg"\r\n'
    "Content-Type: image/jpeg\r\n\r\n"
).encode()
#: Absolute POSIX paths: a slash that starts a word, then a name (never "image/jpeg" or "0..90").
ABSOLUTE_PATH = re.compile(r"(?<![\w.:/-])/[\w.-]+/")


@pytest.fixture(scope="module")
def server(tmp_path_factory, fitted_models):
    """The default upload limit (30 MB per image); a whole POST /references bounded at 40 MB."""
    env = {"GEOLOC_MAX_REQUEST_BYTES": str(40 * MB)}
    with Server(tmp_path_factory.mktemp("hardening") / "data", fitted_models, api_key=KEY, extra_env=env) as s:
        r = s.client.post(
            "/references",
            files=[("image", ("first.jpg", CROP, "image/jpeg"))],
            data={"lat": 39.95, "lon": -75.19, "label": "first"},
            headers={"X-API-Key": KEY},
        )
        assert r.status_code == 202, r.text
        wait_job(s.client, r.json()["job_id"])
        s.ref_id = r.json()["reference_ids"][0]
        yield s


def _stream(url: str, headers: dict, content_length: bool) -> tuple[httpx.Response, int]:
    """POST a 300 MB multipart body that never ends its image part; returns the answer and how many
    bytes the client had handed to the socket when the server answered (and stopped reading)."""
    sent = 0

    def body():
        nonlocal sent
        yield PREAMBLE
        sent += len(PREAMBLE)
        chunk = bytes(MB)
        while sent < TOTAL:
            n = min(len(chunk), TOTAL - sent)
            yield chunk[:n]
            sent += n  # resumed only once the previous chunk was written

    h = {"Content-Type": f"multipart/form-data; boundary={BOUNDARY}", **headers}
    if content_length:
        h["Content-Length"] = str(TOTAL)  # else httpx sends it chunked
    with httpx.Client(timeout=120) as c:
        r = c.post(url, content=body(), headers=h)
    return r, sent


@pytest.mark.parametrize("content_length", [False, True], ids=["chunked", "content-length"])
@pytest.mark.parametrize(
    "path, key, expected",
    [
        ("/references", None, "unauthorized"),
        ("/references", KEY, "too_large"),
        ("/locate", None, "too_large"),
        ("/locate", KEY, "too_large"),
    ],
    ids=["references-no-key", "references-key", "locate-no-key", "locate-key"],
)
def test_a_300_mb_body_is_answered_before_64_mb_are_read(server, path, key, expected, content_length):
    headers = {"X-API-Key": key} if key else {}
    r, sent = _stream(server.url + path, headers, content_length)
    assert r.status_code == (401 if expected == "unauthorized" else 413), r.text
    assert r.json()["error"] == expected and set(r.json()) == {"error", "message"}
    print(f"{path} key={bool(key)} content_length={content_length}: answered after {sent / MB:.1f} MB")
    assert sent < READ_AT_MOST, f"the server read {sent / MB:.0f} MB before answering"
    assert server.client.get("/health").status_code == 200


def test_uploads_within_the_limits_still_work(server):
    c = server.client
    h = {"X-API-Key": KEY}
    q = c.post("/locate", files=[("image", ("q.jpg", CROP, "image/jpeg"))], data={"top_k": 3})
    assert q.status_code == 200 and q.json()["candidates"], q.text
    photo = (PENN / "photos" / "img_00002.jpg").read_bytes()
    r = c.post(
        "/references", files=[("image", ("p.jpg", photo, "image/jpeg"))], data={"lat": 39.95, "lon": -75.19}, headers=h
    )
    assert r.status_code == 202, r.text
    assert wait_job(c, r.json()["job_id"])["status"] == "done"
    # A part of exactly the per-image limit passes the body limit: judged as an image (not one), not as a size.
    r = c.post("/locate", files=[("image", ("z.jpg", bytes(30 * MB), "image/jpeg"))])
    assert r.status_code == 400 and r.json()["error"] == "unreadable_image", r.text
    r = c.patch(f"/references/{server.ref_id}", json={"label": "first"}, headers=h)
    assert r.status_code == 200, r.text


def _client_port(r: httpx.Response) -> int:
    return r.extensions["network_stream"].get_extra_info("client_addr")[1]


@pytest.mark.parametrize(
    "metadata",
    [
        '[{"lat":1' + "0" * 400 + ',"lon":1}]',  # was float(): OverflowError, a 500
        "[" * 100_000,  # was json.loads: RecursionError, a 500
        "[" * 1_000 + "]" * 1_000,  # short enough for the length bound: the parser's depth guard
        json.dumps([{"lat": 39.95, "lon": -75.19, "label": "x" * 100}]) + " " * 100_000,  # over the length bound
    ],
    ids=["overflow", "deep-100k", "deep-1k", "long"],
)
def test_metadata_that_broke_the_parser_is_a_422_on_the_same_connection(server, metadata):
    with httpx.Client(base_url=server.url, headers={"X-API-Key": KEY}, timeout=60) as c:
        before = c.get("/references").json()["total"]
        r = c.post("/references", files=[("image", ("a.jpg", CROP, "image/jpeg"))], data={"metadata": metadata})
        assert r.status_code == 422 and r.json()["error"] in ("invalid_request", "invalid_position"), r.text
        port = _client_port(r)
        after = c.get("/references")
        assert _client_port(after) == port, "the keep-alive connection was dropped"
        assert after.json()["total"] == before


def _via_form(field: str, value) -> dict:
    return {"data": {"lat": 39.95, "lon": -75.19, field: value}}


def _via_metadata(field: str, value) -> dict:
    return {"data": {"metadata": json.dumps([{"lat": 39.95, "lon": -75.19, field: value}])}}


BAD_FIELDS = [
    ("lat", True),
    ("lon", False),
    ("heading", True),
    ("label", "x" * 10_000),
    ("captured_at", "2024-01-01T00:00:00Z" * 10),
    ("captured_at", {"a": 1}),
    ("label", ["a"]),
    ("label", "a\x00b"),
    ("label", "photo\u202egpj.exe"),
    ("label", "line\nbreak"),
    ("captured_at", "2024\u20661"),
    ("captured_at", "\x1b[31m2024"),
]


@pytest.mark.parametrize("field, value", BAD_FIELDS, ids=[f"{f}-{n}" for n, (f, _) in enumerate(BAD_FIELDS)])
def test_bad_fields_are_422_via_metadata_form_and_patch(server, field, value):
    c = server.client
    h = {"X-API-Key": KEY}
    before = c.get("/references").json()["total"]
    stored = c.get(f"/references/{server.ref_id}").json()
    ways = [_via_metadata(field, value)]
    if isinstance(value, str):  # a form field is a string by nature
        ways.append(_via_form(field, value))
    elif isinstance(value, bool):
        ways.append(_via_form(field, json.dumps(value)))
    photo = (PENN / "crops" / "img_00003_0.jpg").read_bytes()  # not stored yet: a real addition
    for way in ways:
        r = c.post("/references", files=[("image", ("new.jpg", photo, "image/jpeg"))], headers=h, **way)
        assert r.status_code == 422 and r.json()["error"] in ("invalid_request", "invalid_position"), (way, r.text)
        assert field in r.json()["message"] or "metadata has" in r.json()["message"], r.text  # or its length
    r = c.patch(f"/references/{server.ref_id}", json={field: value}, headers=h)
    assert r.status_code == 422 and r.json()["error"] == "invalid_request", r.text
    assert c.get("/references").json()["total"] == before
    assert c.get(f"/references/{server.ref_id}").json() == stored


def test_a_file_name_with_control_characters_is_refused(server):
    c = server.client
    before = c.get("/references").json()["total"]
    photo = (PENN / "crops" / "img_00003_1.jpg").read_bytes()
    for name in ("photo\u202egpj.jpg".encode(), b"bell\x07.jpg"):  # httpx would send \x07 as "%07": by hand
        body = (
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="lat"\r\n\r\n39.95\r\n'
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="lon"\r\n\r\n-75.19\r\n'
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="image"; filename="'
        ).encode()
        body += name + b'"\r\nContent-Type: image/jpeg\r\n\r\n' + photo + f"\r\n--{BOUNDARY}--\r\n".encode()
        r = c.post(
            "/references",
            content=body,
            headers={"X-API-Key": KEY, "Content-Type": f"multipart/form-data; boundary={BOUNDARY}"},
        )
        assert r.status_code == 422 and r.json()["error"] == "invalid_request", (name, r.text)
        assert "file name" in r.json()["message"], r.text
    # The same file under a label: the file name is not stored, so it does not matter.
    r = c.post(
        "/references",
        files=[("image", ("photo\u202egpj.jpg", photo, "image/jpeg"))],
        data={"lat": 39.95, "lon": -75.19, "label": "Locust Walk"},
        headers={"X-API-Key": KEY},
    )
    assert r.status_code == 202, r.text
    wait_job(c, r.json()["job_id"])
    assert c.get("/references").json()["total"] == before + 1


def test_a_503_names_no_server_path(server, tmp_path):
    images = server.data_dir / "images"
    moved = tmp_path / "images.moved"
    images.rename(moved)
    images.write_bytes(b"a file where the images folder should be")
    try:
        r = server.client.post(
            "/references",
            files=[("image", ("x.jpg", (PENN / "crops" / "img_00004_0.jpg").read_bytes(), "image/jpeg"))],
            data={"lat": 39.95, "lon": -75.19},
            headers={"X-API-Key": KEY},
        )
    finally:
        images.unlink()
        moved.rename(images)
    assert r.status_code == 503 and r.json()["error"] == "storage_unavailable", r.text
    assert str(server.data_dir) not in r.text and not ABSOLUTE_PATH.search(r.json()["message"]), r.text
    assert str(server.data_dir) in server.read_log()  # the operator still sees where


def test_a_bug_answers_json_500_and_keeps_the_connection():
    """The last resort (app/api/errors.py LastResort) under a real uvicorn: an exception no handler takes
    answers the API's JSON 500 and the keep-alive connection serves the next request."""
    import threading
    import time

    import uvicorn
    from starlette.responses import JSONResponse

    from app.api.errors import LastResort
    from tools.server_process import free_port

    async def buggy(scope, receive, send):
        if scope["path"] == "/bug":
            raise RecursionError("maximum recursion depth exceeded")
        await JSONResponse({"ok": True})(scope, receive, send)

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(LastResort(buggy), port=port, lifespan="off", log_level="critical"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.time() + 30
        while not server.started and time.time() < deadline:
            time.sleep(0.05)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}") as c:
            r = c.get("/bug")
            assert r.status_code == 500 and r.json()["error"] == "internal_error", r.text
            assert "RecursionError" in r.json()["message"]
            assert _client_port(c.get("/fine")) == _client_port(r)
    finally:
        server.should_exit = True
        thread.join(10)
