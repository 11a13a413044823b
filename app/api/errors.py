"""Domain errors to HTTP status codes, and one JSON error shape: {"error": code, "message": text}.

The codes are a frozen, documented list (``ERRORS``): clients branch on them, so a code is snake_case,
has one HTTP status and one meaning, and is never renamed. The engine raises its own exception classes
(``UnreadableImage``, ...); only this module turns them into codes, so the engine's class names never
leak into the API. The error table of docs/api.md and the OpenAPI document are checked against this list."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.engine import errors as e
from app.errors import code_of

log = logging.getLogger("geoloc.api")


@dataclass(frozen=True)
class ErrorCode:
    status: int
    meaning: str


#: Every code the API answers with. Add to it, never rename or re-purpose an entry.
ERRORS: dict[str, ErrorCode] = {
    "malformed_request": ErrorCode(
        400, "the body could not be parsed (a broken or truncated multipart form, a JSON body that is not JSON)"
    ),
    "unreadable_image": ErrorCode(400, "the bytes are not an image we can decode (empty, truncated, not an image)"),
    "unauthorized": ErrorCode(401, "the call needs a valid X-API-Key header"),
    "not_found": ErrorCode(404, "no such reference, job or path"),
    "image_missing": ErrorCode(404, "the reference exists but its stored image file is gone (see `geoloc check`)"),
    "method_not_allowed": ErrorCode(405, "the path exists but not with this HTTP method"),
    "too_large": ErrorCode(
        413, "an uploaded image (or the request body) has too many bytes, or an image too many pixels"
    ),
    "too_many_files": ErrorCode(413, "more images in one request than GEOLOC_MAX_FILES_PER_REQUEST"),
    "unsupported_image_format": ErrorCode(415, "a real image in a format we do not accept (e.g. GIF, HEIC)"),
    "invalid_request": ErrorCode(422, "a parameter or field is missing, malformed or out of range"),
    "image_too_small": ErrorCode(422, "too few pixels to describe a place"),
    "image_shape": ErrorCode(422, "too long and thin to describe a place: one side over 10 times the other"),
    "no_gps_in_image": ErrorCode(422, "no position was given and the photo has no EXIF GPS position"),
    "invalid_position": ErrorCode(
        422, "latitude/longitude out of range or not finite (an upload's, an edit's or a search region's)"
    ),
    "unsupported_mode": ErrorCode(422, "the search mode is not available in the served configuration"),
    "internal_error": ErrorCode(500, "a bug: the server log has the traceback"),
    "not_ready": ErrorCode(503, "the model, fitted pipeline or index is not loaded (yet): see /ready"),
    "storage_unavailable": ErrorCode(503, "the data dir cannot be written (disk full, read-only, permissions)"),
}

#: Refusals raised by Starlette/FastAPI themselves (routing, multipart parsing, static files).
FRAMEWORK_CODES: dict[int, str] = {
    400: "malformed_request",
    401: "unauthorized",
    404: "not_found",
    405: "method_not_allowed",
    413: "too_large",
}

ErrorCodeName = Literal[tuple(ERRORS)]  # type: ignore[valid-type]  # the OpenAPI enum of ErrorBody.error


class ErrorBody(BaseModel):
    error: ErrorCodeName = Field(description="one of the frozen codes listed in the API description")
    message: str = Field(description="what went wrong, in words, for a person")


class ApiError(Exception):
    """A refusal decided in the HTTP layer. ``error`` must be a code of ``ERRORS`` with its status, written as
    literals so that tests/api/test_errors.py can check every call."""

    def __init__(self, status: int, error: str, message: str):
        self.status, self.error, self.message = status, error, message


def domain_code(exc: Exception) -> str:
    """The code of a service or engine error (``app.errors.code_of``: each error carries or maps to one)."""
    return code_of(exc)


def framework_code(status: int) -> str:
    """The code of a framework refusal; an unknown status folds into the nearest listed one."""
    return FRAMEWORK_CODES.get(status, "malformed_request" if status < 500 else "internal_error")


def codes_markdown() -> str:
    """The frozen list as a Markdown table (the API description on /docs shows it)."""
    rows = [f"| `{code}` | {c.status} | {c.meaning} |" for code, c in ERRORS.items()]
    return "\n".join(["| error | HTTP | meaning |", "|---|---|---|", *rows])


def error_responses(*codes: int) -> dict:
    """OpenAPI entries so /openapi.json documents every error a route can answer, with the codes per status."""
    out = {}
    for status in codes:
        names = [f"`{n}`" for n, c in ERRORS.items() if c.status == status]
        out[status] = {"model": ErrorBody, "description": ", ".join(names) or "error"}
    return out


#: An absolute POSIX path: a slash that starts a word (not "image/jpeg", not "http://"), then a name and more.
_ABSOLUTE_PATH = re.compile(r"(?<![\w.:/-])/(?:[^/\s'\"]+/)+([^/\s'\"]*)")


def without_paths(message: str) -> str:
    """The message with each absolute path cut to its last name ("…/images"): an answer tells a client what
    failed, not where the server keeps its files (the server log keeps the whole path)."""
    return _ABSOLUTE_PATH.sub(lambda m: "…/" + m.group(1), message)


def error_response(error: str, message: str, status: int | None = None, headers: dict | None = None) -> JSONResponse:
    """The one error shape; every error body goes through here (so none names a server path)."""
    body = {"error": error, "message": without_paths(message)}
    return JSONResponse(body, status_code=status or ERRORS[error].status, headers=headers)


_json = error_response


def install(
    app: FastAPI, storage_exceptions: tuple[type[Exception], ...], is_storage_error: Callable[[BaseException], bool]
) -> None:
    """Every error answers JSON with its code. ``storage_exceptions``: the storage backend's raw error types
    (``StorageBackend.exceptions``), a 503 when one escapes ``storage_guard``; ``is_storage_error``: whether
    an escaped error is the storage's own (``StorageBackend.unavailable``), a 503 too, else a 500."""

    @app.exception_handler(ApiError)
    async def _api(_: Request, exc: ApiError):
        return _json(exc.error, exc.message, exc.status)

    @app.exception_handler(e.GeolocError)
    async def _domain(_: Request, exc: e.GeolocError):
        code = domain_code(exc)
        if code == "storage_unavailable":
            log.warning("storage unavailable: %s", exc)
        if code == "internal_error":
            log.error("domain error %s has no API code: give it a code in app/errors.py", type(exc).__name__)
        return _json(code, str(exc))

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError):
        # A body that is not JSON at all is a broken body, like a broken form (malformed_request, 400); a
        # JSON body with a wrong field is a refused request (invalid_request, 422).
        broken = [
            err for err in exc.errors() if err.get("type") == "json_invalid" and err.get("loc", ())[:1] == ("body",)
        ]
        if broken:
            why = (broken[0].get("ctx") or {}).get("error") or broken[0].get("msg")
            return _json("malformed_request", f"the body is not valid JSON: {why}")
        parts = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err.get("loc", []) if x not in ("body", "query", "path", "form"))
            parts.append(f"{loc or 'request'}: {err.get('msg')}")
        return _json("invalid_request", "; ".join(parts) or "invalid request")

    async def _storage(_: Request, exc: Exception):
        """Raw storage failures from any path: a 503 the client can retry, answered like any other error
        (a handler for ``Exception`` itself would answer and then drop the keep-alive connection)."""
        if is_storage_error(exc):
            log.warning("storage unavailable: %s", exc)
            return _json("storage_unavailable", f"the data dir cannot be used right now ({exc}); retry later")
        log.exception("unhandled error", exc_info=exc)
        return _json("internal_error", f"internal error ({type(exc).__name__}); see the server log")

    app.add_exception_handler(OSError, _storage)
    for kind in storage_exceptions:  # the backend's raw errors (app.storage.backend)
        app.add_exception_handler(kind, _storage)

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception):
        """Outermost: a bug in a middleware itself. Starlette answers, then drops the connection."""
        log.exception("unhandled error", exc_info=exc)
        return _json("internal_error", f"internal error ({type(exc).__name__}); see the server log")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException):
        message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        return _json(framework_code(exc.status_code), message, headers=exc.headers)  # 405 keeps its Allow


class LastResort:
    """A pure ASGI middleware: an exception no handler took (a bug) answers JSON 500 ``internal_error`` and
    the keep-alive connection stays open. Starlette's own ``Exception`` handler answers too, but re-raises,
    and uvicorn then drops the connection: the client's next request fails on a closed socket."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, tracked)
        except Exception as exc:
            if started:  # half an answer is out: only closing can tell the client
                raise
            log.exception("unhandled error", exc_info=exc)
            response = _json("internal_error", f"internal error ({type(exc).__name__}); see the server log")
            await response(scope, receive, send)
