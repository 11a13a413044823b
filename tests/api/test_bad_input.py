"""Bad input gets a clear 4xx JSON answer and loses nothing already stored."""

import io

import pytest
from PIL import Image

from tests.api.conftest import Server, wait_job
from tests.conftest import PENN

KEY = "k"


@pytest.fixture(scope="module", params=["sqlite", "postgres"])
def server(request, tmp_path_factory, fitted_models):
    """One server per engine of the store: every test here runs on SQLite and on PostgreSQL."""
    env = {}
    if request.param == "postgres":
        env["GEOLOC_DATABASE_URL"] = request.getfixturevalue("postgres_server").create_database()
    s = Server(tmp_path_factory.mktemp("bad") / "data", fitted_models, api_key=KEY, extra_env=env)
    s.wait_ready()
    crop = (PENN / "crops" / "img_00000_0.jpg").read_bytes()
    r = s.client.post(
        "/references",
        files=[("image", ("a.jpg", crop))],
        data={"lat": 39.95, "lon": -75.19},
        headers={"X-API-Key": KEY},
    )
    wait_job(s.client, r.json()["job_id"])
    yield s
    s.stop()


def _png(w, h, mode="RGB"):
    buf = io.BytesIO()
    Image.new(mode, (w, h)).save(buf, "PNG")
    return buf.getvalue()


CROP = (PENN / "crops" / "img_00001_0.jpg").read_bytes()


@pytest.mark.parametrize(
    "files, data, status, words",
    [
        ([("image", ("a.jpg", b""))], {"lat": 1, "lon": 1}, 400, "empty"),
        ([("image", ("a.jpg", b"hello, I am text"))], {"lat": 1, "lon": 1}, 400, "not a JPEG"),
        ([("image", ("a.jpg", CROP[: len(CROP) // 2]))], {"lat": 1, "lon": 1}, 400, "truncated"),
        ([("image", ("a.png", _png(1, 1)))], {"lat": 1, "lon": 1}, 422, "at least"),
        ([("image", ("a.jpg", CROP))], {"lat": 91, "lon": 1}, 422, "out of range"),
        ([("image", ("a.jpg", CROP))], {"lat": 1, "lon": 181}, 422, "out of range"),
        ([("image", ("a.jpg", CROP))], {"lat": "nan", "lon": 1}, 422, "out of range"),
        ([("image", ("a.jpg", CROP))], {"lat": "north", "lon": 1}, 422, "lat"),
        ([("image", ("a.jpg", CROP))], {"lat": 1}, 422, "both lat and lon"),
        ([("image", ("a.jpg", CROP))], {}, 422, "no GPS"),
        ([], {"lat": 1, "lon": 1}, 422, "image"),
        ([("image", ("a.jpg", CROP))] * 51, {"lat": 1, "lon": 1}, 413, "limit"),
        ([("image", ("a.jpg", CROP))], {"metadata": "[{"}, 422, "not valid JSON"),
        ([("image", ("a.jpg", CROP))], {"metadata": "[]"}, 422, "one per image"),
        ([("image", ("../../etc/passwd", CROP))], {"lat": 91, "lon": 0}, 422, "out of range"),
    ],
)
def test_bad_uploads(server, files, data, status, words):
    before = server.client.get("/references").json()["total"]
    r = server.client.post("/references", files=files or None, data=data, headers={"X-API-Key": KEY})
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"error", "message"} and words.lower() in body["message"].lower(), body
    assert server.client.get("/references").json()["total"] == before


def test_keys_ids_modes_and_formats(server):
    c = server.client
    assert c.post("/references", files=[("image", ("a.jpg", CROP))], data={"lat": 1, "lon": 1}).status_code == 401
    assert (
        c.post(
            "/references", files=[("image", ("a.jpg", CROP))], data={"lat": 1, "lon": 1}, headers={"X-API-Key": "wrong"}
        ).status_code
        == 401
    )
    assert c.get("/references/999999").status_code == 404
    assert c.get("/references/abc").status_code == 422
    assert c.get("/jobs/nope").status_code == 404
    assert c.get("/references", params={"offset": 10**30}).status_code == 422  # found by the fuzzer: was a 500
    assert c.delete("/references/999999", headers={"X-API-Key": KEY}).status_code == 404
    r = c.post("/locate", files=[("image", ("q.jpg", CROP))], data={"mode": "sideways"})
    assert r.json()["error"] == "unsupported_mode" and "serves two-stage" in r.json()["message"], r.text
    assert c.post("/locate", files=[("image", ("q.jpg", CROP))], data={"top_k": 1000}).status_code == 422
    assert c.post("/locate", files=[("image", ("q.jpg", CROP))], data={"bbox": "1,2,3"}).status_code == 422
    gif = io.BytesIO()
    frames = [Image.new("P", (64, 64), i) for i in range(2)]
    frames[0].save(gif, "GIF", save_all=True, append_images=frames[1:])
    r = c.post("/locate", files=[("image", ("q.gif", gif.getvalue()))])
    assert r.status_code == 415
    heic = b"\0\0\0\x18ftypheic" + b"\0" * 64
    assert c.post("/locate", files=[("image", ("q.heic", heic))]).status_code == 415
    bomb = c.post("/locate", files=[("image", ("b.png", _bomb_png()))])
    assert bomb.status_code == 413
    malformed = c.post(
        "/locate",
        content=b"--xyz\r\nnot really multipart",
        headers={"Content-Type": "multipart/form-data; boundary=xyz"},
    )
    assert 400 <= malformed.status_code < 500
    for mode in ("CMYK", "L", "RGBA", "I;16"):
        buf = io.BytesIO()
        img = Image.open(io.BytesIO(CROP)).convert("RGB")
        (img.convert(mode) if mode != "I;16" else img.convert("L").convert("I;16")).save(
            buf, "TIFF" if mode == "CMYK" else "PNG"
        )
        r = c.post("/locate", files=[("image", ("q", buf.getvalue()))])
        assert r.status_code == 200, (mode, r.text)
    assert c.get("/references").json()["total"] == 1


def _bomb_png() -> bytes:
    import struct
    import zlib

    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", 30000, 30000, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")
