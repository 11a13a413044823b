"""Domain errors to HTTP status codes, and one JSON error shape: {"error": code, "message": text}."""

from __future__ import annotations

import logging
import sqlite3

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.core import InvalidRequest
from app.engine import errors as e
from app.engine.configs import UnknownConfig
from app.engine.search import UnsupportedMode
from app.store import StorageUnavailable, is_storage_error

log = logging.getLogger("geoloc.api")

STATUS = {
    e.UnreadableImage: 400,
    e.ImageTooSmall: 422,
    e.ImageTooLarge: 413,
    e.UnsupportedImageFormat: 415,
    e.NoGpsInImage: 422,
    e.InvalidPosition: 422,
    UnsupportedMode: 422,
    UnknownConfig: 422,
    e.ModelNotReady: 503,
    InvalidRequest: 422,
    StorageUnavailable: 503,
}
#: Errors whose code is not their class name.
CODES = {InvalidRequest: "invalid_request", StorageUnavailable: "storage_unavailable"}


class ErrorBody(BaseModel):
    error: str
    message: str


class ApiError(Exception):
    def __init__(self, status: int, error: str, message: str):
        self.status, self.error, self.message = status, error, message


def error_responses(*codes: int) -> dict:
    """OpenAPI entries so /openapi.json documents every error a route can answer."""
    text = {
        400: "unreadable input",
        401: "missing or wrong API key",
        404: "not found",
        413: "too large",
        415: "unsupported image format",
        422: "invalid parameters",
        503: "not ready, or the storage is unavailable (retry later)",
    }
    return {c: {"model": ErrorBody, "description": text.get(c, "error")} for c in codes}


def _json(status: int, error: str, message: str) -> JSONResponse:
    return JSONResponse({"error": error, "message": message}, status_code=status)


def install(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api(_: Request, exc: ApiError):
        return _json(exc.status, exc.error, exc.message)

    @app.exception_handler(e.GeolocError)
    async def _domain(_: Request, exc: e.GeolocError):
        status = next((s for t, s in STATUS.items() if isinstance(exc, t)), 400)
        code = next((c for t, c in CODES.items() if isinstance(exc, t)), type(exc).__name__)
        if isinstance(exc, StorageUnavailable):
            log.warning("storage unavailable: %s", exc)
        return _json(status, code, str(exc))

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError):
        parts = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err.get("loc", []) if x not in ("body", "query", "path", "form"))
            parts.append(f"{loc or 'request'}: {err.get('msg')}")
        return _json(422, "invalid_request", "; ".join(parts) or "invalid request")

    async def _storage(_: Request, exc: Exception):
        """Raw storage failures from any path: a 503 the client can retry, answered like any other error
        (a handler for ``Exception`` itself would answer and then drop the keep-alive connection)."""
        if is_storage_error(exc):
            log.warning("storage unavailable: %s", exc)
            return _json(503, "storage_unavailable", f"the data dir cannot be used right now ({exc}); retry later")
        log.exception("unhandled error", exc_info=exc)
        return _json(500, "internal_error", f"internal error ({type(exc).__name__}); see the server log")

    app.add_exception_handler(OSError, _storage)
    app.add_exception_handler(sqlite3.Error, _storage)

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception):
        """A bug still answers in the API's JSON shape; the traceback goes to the server log."""
        log.exception("unhandled error", exc_info=exc)
        return _json(500, "internal_error", f"internal error ({type(exc).__name__}); see the server log")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException):
        message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        return _json(
            exc.status_code, {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error"), message
        )
