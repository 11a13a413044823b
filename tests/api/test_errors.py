"""The error codes: one frozen list, snake_case, each with one HTTP status, and nothing outside it.

Checked three ways: statically (every ``ApiError`` the code base raises, every domain exception class,
every framework refusal), on a real server (requests that provoke each kind of error), and in the
documents people read (the README's table, the OpenAPI description and the ErrorBody enum)."""

import ast
import importlib
import io
import pkgutil
import re

import pytest
from PIL import Image

import app as app_pkg
from app.api.errors import ERRORS, FRAMEWORK_CODES, domain_code, framework_code
from app.engine.errors import GeolocError
from app.errors import ENGINE_CODES, ServiceError
from tests.api.conftest import Server
from tests.conftest import PENN, REPO

SNAKE = re.compile(r"[a-z]+(_[a-z]+)*")
CROP = (PENN / "crops" / "img_00001_0.jpg").read_bytes()


def test_codes_are_snake_case_with_a_status_and_a_meaning():
    assert len(ERRORS) == len(set(ERRORS))
    for code, c in ERRORS.items():
        assert SNAKE.fullmatch(code), code
        assert 400 <= c.status < 600 and c.meaning, code
    assert "storage_unavailable" in ERRORS and ERRORS["storage_unavailable"].status == 503
    assert "duplicate" not in ERRORS  # a stored duplicate is an answer, not an error


def _api_error_calls():
    """(file, line, status, code) of every ``ApiError(status, "code", ...)`` in app/."""
    for path in sorted((REPO / "app").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "ApiError":
                status, code = node.args[0], node.args[1]
                assert isinstance(status, ast.Constant) and isinstance(code, ast.Constant), (
                    f"{path}:{node.lineno}: ApiError needs a literal status and code, so this test can check them"
                )
                yield f"{path.name}:{node.lineno}", status.value, code.value


def test_every_raised_api_error_uses_a_listed_code_with_its_status():
    calls = list(_api_error_calls())
    assert len(calls) >= 10  # the routes raise them: an empty scan would prove nothing
    for where, status, code in calls:
        assert code in ERRORS, f"{where}: {code!r} is not in the frozen list (app/api/errors.py ERRORS)"
        assert ERRORS[code].status == status, f"{where}: {code} is {ERRORS[code].status}, not {status}"


def _all_subclasses(cls):
    for sub in cls.__subclasses__():
        yield sub
        yield from _all_subclasses(sub)


def test_every_domain_exception_maps_to_a_listed_code():
    for mod in pkgutil.walk_packages(app_pkg.__path__, "app."):  # so every subclass is defined
        importlib.import_module(mod.name)
    classes = [c for c in _all_subclasses(GeolocError) if c is not ServiceError]  # the base has no code
    assert len(classes) >= 10
    for cls in classes:
        code = domain_code(cls("x"))
        assert code in ERRORS and code != "internal_error", f"{cls.__name__} has no API code"
    assert set(ENGINE_CODES.values()) <= set(ERRORS)
    assert {c.code for c in _all_subclasses(ServiceError)} <= set(ERRORS)
    assert domain_code(GeolocError("unlisted")) == "internal_error"


def test_framework_refusals_map_to_listed_codes_with_their_status():
    for status, code in FRAMEWORK_CODES.items():
        assert ERRORS[code].status == status
    assert framework_code(418) == "malformed_request" and framework_code(502) == "internal_error"


def test_the_api_page_lists_every_code_with_its_status():
    api = (REPO / "docs" / "api.md").read_text()
    for code, c in ERRORS.items():
        rows = [line for line in api.splitlines() if line.startswith(f"| `{code}` |")]
        assert rows, f"docs/api.md has no row for {code}"
        assert f"| {c.status} |" in rows[0], rows[0]


def _png(w: int, h: int) -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (w, h)).save(buf, "PNG")
    return buf.getvalue()


def _gif() -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (300, 300)).save(buf, "GIF")
    return buf.getvalue()


@pytest.fixture(scope="module")
def server(tmp_path_factory, fitted_models):
    # A small upload limit so that a real photo provokes too_large.
    env = {"GEOLOC_MAX_UPLOAD_BYTES": str(len(CROP) * 4)}
    with Server(tmp_path_factory.mktemp("errors") / "data", fitted_models, extra_env=env) as s:
        yield s


def test_a_real_server_answers_listed_codes(server):
    c = server.client  # it sends the data dir's key: these are refusals of the request, not of the caller
    photo = (PENN / "photos" / "img_00008.jpg").read_bytes()
    ref = {"lat": 39.95, "lon": -75.19}
    cases = [
        (c.post("/locate", files=[("image", ("a.jpg", b"I am text"))]), "unreadable_image"),
        (c.post("/locate", files=[("image", ("a.gif", _gif()))]), "unsupported_image_format"),
        (c.post("/locate", files=[("image", ("a.png", _png(4, 4)))]), "image_too_small"),
        (c.post("/locate", files=[("image", ("a.jpg", photo))]), "too_large"),
        (c.post("/locate", files=[("image", ("a.jpg", CROP))], data={"top_k": 10_000}), "invalid_request"),
        (c.post("/references", files=[("image", ("a.jpg", CROP))]), "no_gps_in_image"),
        (
            c.post("/references", files=[("image", ("a.jpg", CROP))], data=ref, headers={"X-API-Key": "no"}),
            "unauthorized",
        ),
        (
            c.post(
                "/locate",
                content=b"--xx\r\nbroken",
                headers={"Content-Type": "multipart/form-data"},  # no boundary: the parser gives up
            ),
            "malformed_request",
        ),
        (c.get("/references/999999"), "not_found"),
        (c.get("/no/such/path"), "not_found"),
        (c.put("/locate"), "method_not_allowed"),
    ]
    for r, expected in cases:
        body = r.json()
        assert set(body) == {"error", "message"}, (expected, body)
        assert body["error"] == expected and r.status_code == ERRORS[expected].status, (expected, r.status_code, body)


def test_openapi_documents_the_codes(server):
    spec = server.client.get("/openapi.json").json()
    assert spec["components"]["schemas"]["ErrorBody"]["properties"]["error"]["enum"] == list(ERRORS)
    for code in ERRORS:
        assert f"`{code}`" in spec["info"]["description"], code
    assert "`unauthorized`" in spec["paths"]["/references"]["post"]["responses"]["401"]["description"]
