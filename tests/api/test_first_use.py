"""What a newcomer trips on: one fault gets one code on every route, capture times are ISO 8601,
answers carry rounded figures, and the mode refusal says which configuration would serve the mode."""

import json

import httpx
import pytest

from app.engine.configs import CONFIGS, configs_serving, get_config
from app.engine.index.references import ReferenceIndex, UnsupportedMode
from tests.api.conftest import Server, wait_job
from tests.conftest import PENN

KEY = "first-use-key"
BOUNDARY = "geolocboundary22"
PHOTO = PENN / "photos" / "img_00000.jpg"  # EXIF: GPS, 2024:09:23 16:06:58, OffsetTimeOriginal -04:00
CROP = (PENN / "crops" / "img_00000_0.jpg").read_bytes()  # no EXIF at all


@pytest.fixture(scope="module")
def server(tmp_path_factory, fitted_models):
    s = Server(tmp_path_factory.mktemp("first-use") / "data", fitted_models, api_key=KEY)
    s.wait_ready()
    h = {"X-API-Key": KEY}
    r = s.client.post("/references", files=[("image", ("p.jpg", PHOTO.read_bytes(), "image/jpeg"))], headers=h)
    assert r.status_code == 202, r.text
    s.ref_id = r.json()["reference_ids"][0]
    r = s.client.post(
        "/references",
        files=[("image", ("c.jpg", CROP, "image/jpeg"))],
        data={"lat": 39.95165, "lon": -75.19225, "captured_at": "2024:09:23 16:08:20"},  # EXIF's form, typed
        headers=h,
    )
    s.crop_id = r.json()["reference_ids"][0]
    wait_job(s.client, r.json()["job_id"])
    yield s
    s.stop()


def _form(fields: dict, image: bytes = CROP) -> bytes:
    body = b"".join(
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode() for k, v in fields.items()
    )
    body += f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="image"; filename="a.jpg"\r\n'.encode()
    return body + b"Content-Type: image/jpeg\r\n\r\n" + image + f"\r\n--{BOUNDARY}--\r\n".encode()


def _post_raw(c: httpx.Client, path: str, body: bytes) -> httpx.Response:
    headers = {"X-API-Key": KEY, "Content-Type": f"multipart/form-data; boundary={BOUNDARY}"}
    return c.post(path, content=body, headers=headers)


def test_one_fault_one_code_on_every_route(server):
    c, h = server.client, {"X-API-Key": KEY}
    before = c.get("/references").json()
    stored = c.get(f"/references/{server.ref_id}").json()
    lat99 = {"lat": 99, "lon": -75.19}
    answers = {
        "POST /references -F lat=99": c.post("/references", files=[("image", ("a.jpg", CROP))], data=lat99, headers=h),
        "POST /references metadata lat=99": c.post(
            "/references", files=[("image", ("a.jpg", CROP))], data={"metadata": json.dumps([lat99])}, headers=h
        ),
        "PATCH lat=99": c.patch(f"/references/{server.ref_id}", json={"lat": 99}, headers=h),
        "PATCH lon=-181": c.patch(f"/references/{server.ref_id}", json={"lon": -181}, headers=h),
        "POST /locate region lat=99": c.post(
            "/locate", files=[("image", ("a.jpg", CROP))], data={"lat": 99, "lon": 1, "radius_m": 300}
        ),
        "POST /locate bbox lat=99": c.post(
            "/locate", files=[("image", ("a.jpg", CROP))], data={"bbox": "-75.2,39.9,-75.1,99"}
        ),
        "GET /references bbox lat=99": c.get("/references", params={"bbox": "-75.2,39.9,-75.1,99"}),
    }
    for way, r in answers.items():
        assert r.status_code == 422 and r.json()["error"] == "invalid_position", (way, r.text)

    # A multipart body cut short (no closing boundary) is a broken form on both routes, whatever it held.
    for path, fields in (("/locate", {"top_k": 3}), ("/references", {"lat": 39.95, "lon": -75.19})):
        whole = _form(fields)
        for cut in (len(whole) // 2, len(whole) - 8, 40):
            r = _post_raw(c, path, whole[:cut])
            assert r.status_code == 400 and r.json()["error"] == "malformed_request", (path, cut, r.text)
            assert "cut short" in r.json()["message"]
    assert _post_raw(c, "/locate", _form({"top_k": 3})).status_code == 200  # the whole body is fine
    # A PATCH body that is not JSON is a broken body too; a JSON body with a bad field is a refused request.
    r = c.patch(
        f"/references/{server.ref_id}", content=b'{"lat": 39.9', headers={**h, "Content-Type": "application/json"}
    )
    assert r.status_code == 400 and r.json()["error"] == "malformed_request", r.text
    r = c.patch(f"/references/{server.ref_id}", json={"heading": 400}, headers=h)
    assert r.status_code == 422 and r.json()["error"] == "invalid_request", r.text

    assert c.get("/references").json()["total"] == before["total"]
    assert c.get(f"/references/{server.ref_id}").json() == stored


def test_captured_at_is_iso_8601_from_exif_forms_and_edits(server):
    c, h = server.client, {"X-API-Key": KEY}
    # From the photo's EXIF (DateTimeOriginal with its OffsetTimeOriginal), and EXIF's form typed in a field.
    assert c.get(f"/references/{server.ref_id}").json()["captured_at"] == "2024-09-23T16:06:58-04:00"
    assert c.get(f"/references/{server.crop_id}").json()["captured_at"] == "2024-09-23T16:08:20"
    located = c.post("/locate", files=[("image", ("q.jpg", PHOTO.read_bytes()))], data={"top_k": 5}).json()
    for cand in located["candidates"]:
        assert cand["captured_at"] in ("2024-09-23T16:06:58-04:00", "2024-09-23T16:08:20"), cand

    for bad in ("yesterday", "2024-13-01", "2024-02-30T10:00:00", "23/09/2024"):
        for way in ("patch", "form", "metadata"):
            if way == "patch":
                r = c.patch(f"/references/{server.crop_id}", json={"captured_at": bad}, headers=h)
            elif way == "form":
                data = {"lat": 39.95, "lon": -75.19, "captured_at": bad}
                r = c.post("/references", files=[("image", ("n.jpg", CROP))], data=data, headers=h)
            else:
                meta = json.dumps([{"lat": 39.95, "lon": -75.19, "captured_at": bad}])
                r = c.post("/references", files=[("image", ("n.jpg", CROP))], data={"metadata": meta}, headers=h)
            assert r.status_code == 422 and r.json()["error"] == "invalid_request", (bad, way, r.text)
            assert (
                "captured_at" in r.json()["message"]
                and "ISO 8601" in r.json()["message"]
                or "real date" in (r.json()["message"])
            ), r.text
    assert c.get(f"/references/{server.crop_id}").json()["captured_at"] == "2024-09-23T16:08:20"
    for given, stored in [
        ("2024-09-23T18:00:00Z", "2024-09-23T18:00:00+00:00"),
        ("2024-09-23 18:00", "2024-09-23T18:00:00"),
        ("2024-09-23", "2024-09-23"),
    ]:
        r = c.patch(f"/references/{server.crop_id}", json={"captured_at": given}, headers=h)
        assert r.status_code == 200 and r.json()["captured_at"] == stored, r.text
    r = c.patch(f"/references/{server.crop_id}", json={"captured_at": "2024:09:23 16:08:20"}, headers=h)
    assert r.json()["captured_at"] == "2024-09-23T16:08:20"


def _decimals(x: float) -> int:
    text = repr(x)
    return len(text.split(".")[1]) if "." in text and "e" not in text else (0 if "e" not in text else 99)


def test_answers_round_metres_and_scores(server):
    r = server.client.post("/locate", files=[("image", ("q.jpg", PHOTO.read_bytes()))], data={"top_k": 5})
    answer = r.json()
    # The tests' pipeline is not calibrated: the conservative rule wants 3 candidates agreeing on
    # one spot, and the photo itself and its crop are 2: no estimate, and it says why.
    assert answer["estimate"] is None and answer["reason_code"] == "ambiguous", answer
    assert answer["reason"].startswith("uncalibrated") and "the best group has 2" in answer["reason"], answer
    for cand in answer["candidates"]:
        assert _decimals(cand["score"]) <= 4, cand
        assert cand["distance_m"] is None and cand["p_within_25m"] is None, cand
    assert answer["candidates"][0]["score"] == 1.0  # the photo's own reference: 1.0, not 0.99999994


def test_unsupported_mode_names_the_configurations_that_serve_it():
    # float codes only, as the default; told which configurations serve a mode, as the pipeline tells it
    index = ReferenceIndex(get_config("hybrid"), float_dim=8, bits=None, serving=configs_serving)
    with pytest.raises(UnsupportedMode) as refused:
        index.check_mode("binary")
    message = str(refused.value)
    serving = [name for name, c in CONFIGS.items() if "binary" in c.modes]
    assert "hybrid-bin" in serving and all(name in message for name in serving), message
    assert "'hybrid'" in message and "serves float" in message and "GEOLOC_CONFIG" in message
    with pytest.raises(UnsupportedMode, match="two-stage are hybrid-bin"):
        index.check_mode("two-stage")
    with pytest.raises(UnsupportedMode, match="not a search mode"):
        index.check_mode("fast")
