"""Request bodies bounded before they are read, and writes' keys checked before their bodies.

FastAPI parses a multipart form (spooling its files to temporary files) before any dependency runs, so a
size check in a route, or the key check of ``write_access``, comes after the whole body has been read: a
large body with no key used to get its 401 only after most of it had been spooled. This pure ASGI middleware runs
first: it finds the route, runs the route's own access dependencies (app/api/deps.py) on the headers,
refuses a declared ``Content-Length`` over the route's limit, and counts the bytes as the app reads them,
answering 413 the moment they pass the limit. A refusal with body bytes still unread closes the
connection (``Connection: close``): uvicorn would otherwise read the rest to reach the next request."""

from __future__ import annotations

from collections.abc import Sequence

from starlette.exceptions import HTTPException
from starlette.requests import HTTPConnection
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.api.deps import ACCESS_CHECKS
from app.api.errors import ApiError, error_response
from app.settings import Settings

#: Multipart framing and the form's text fields (``metadata`` included) around the images.
FORM_OVERHEAD = 1024 * 1024
#: Every other body: JSON (PATCH) or nothing at all.
SMALL_BODY = 64 * 1024


def body_limit(settings: Settings, method: str, path: str | None) -> int:
    """The most bytes a body may have on this route (``path``: the route's template; None: no route)."""
    if method == "POST" and path == "/locate":
        return settings.max_upload_bytes + FORM_OVERHEAD
    if method == "POST" and path == "/locate/sequence":
        images = min(settings.max_upload_bytes * settings.max_sequence_images, settings.max_request_bytes)
        return images + FORM_OVERHEAD
    if method == "POST" and path == "/references":
        images = min(settings.max_upload_bytes * settings.max_files_per_request, settings.max_request_bytes)
        return images + FORM_OVERHEAD
    return SMALL_BODY


class _TooLarge(Exception):
    """Raised into the app from ``receive`` once the body passes its limit; the app's own answer to it
    (FastAPI makes it a 400) is dropped, and the 413 sent instead."""


class BodyLimits:
    """``routes``: the API's routes (the routers' own, whose dependencies name the access checks)."""

    def __init__(self, app: ASGIApp, settings: Settings, routes: Sequence[BaseRoute]):
        self.app = app
        self.settings = settings
        self.routes = list(routes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        conn = HTTPConnection(scope)
        route = _route(self.routes, scope)
        path = getattr(route, "path", None)
        limit = body_limit(self.settings, scope["method"], path)
        declared = _declared_length(conn)
        # Refused unread, a small body is read and dropped by uvicorn (the connection stays); a larger or
        # chunked one is not read at all: the connection closes.
        close = {"Connection": "close"} if declared is None or declared > SMALL_BODY else None
        try:
            for depends in getattr(route, "dependencies", ()):
                if depends.dependency in ACCESS_CHECKS:
                    depends.dependency(conn, conn.headers.get("x-api-key"))
        except ApiError as e:
            await error_response(e.error, e.message, e.status, headers=close)(scope, receive, send)
            return
        if declared is not None and declared > limit:
            await _refuse(limit, path, scope, receive, send)
            return

        received = 0
        refused = False
        started = False
        ending = MultipartEnd.of(conn)

        async def counted() -> Message:
            nonlocal received, refused
            message = await receive()
            if message["type"] == "http.request":
                body = message.get("body", b"")
                received += len(body)
                if received > limit and not started:
                    refused = True
                    raise _TooLarge
                if ending is not None:
                    ending.feed(body, last=not message.get("more_body", False))
            return message

        async def guarded(message: Message) -> None:
            nonlocal started
            if refused:  # the app's answer to the refusal: ours goes out instead
                return
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counted, guarded)
        except Exception:
            if not refused:
                raise
        if refused:
            await _refuse(limit, path, scope, receive, send)


class MultipartEnd:
    """Watches a multipart body for its closing delimiter (``--BOUNDARY--``). A body cut short is parsed by
    python-multipart as far as it goes, without a word: the part in flight is dropped, and the route then
    said "image: Field required" (422 ``invalid_request``) about an image the client did send. A body that
    ends without its closing delimiter is refused instead as what it is, a broken form: 400
    ``malformed_request``."""

    def __init__(self, boundary: bytes):
        self.closing = b"--" + boundary + b"--"
        self.tail = b""
        self.seen = False

    @classmethod
    def of(cls, conn: HTTPConnection) -> MultipartEnd | None:
        """The watcher for a multipart/form-data request with a boundary; None for any other body (one
        without a boundary is refused by the parser itself)."""
        kind, _, params = conn.headers.get("content-type", "").partition(";")
        if kind.strip().lower() != "multipart/form-data":
            return None
        for param in params.split(";"):
            name, _, value = param.strip().partition("=")
            if name.lower() == "boundary" and value.strip('"'):
                return cls(value.strip('"').encode("latin-1"))
        return None

    def feed(self, chunk: bytes, last: bool) -> None:
        if not self.seen:
            window = self.tail + chunk
            self.seen = self.closing in window
            self.tail = window[-(len(self.closing) - 1) :]
        if last and not self.seen:
            raise HTTPException(
                400,
                "the multipart body ends before its closing boundary: the upload was cut short (send it again)",
            )


def _route(routes: Sequence[BaseRoute], scope: Scope) -> BaseRoute | None:
    """The route that will answer (None: no API path matches with this method; a 404 or 405 follows)."""
    for route in routes:
        match, _ = route.matches(scope)
        if match == Match.FULL:
            return route
    return None


def _declared_length(conn: HTTPConnection) -> int | None:
    """The ``Content-Length`` (0 when the request has no body); None when chunked or unreadable."""
    if "transfer-encoding" in conn.headers:
        return None
    value = conn.headers.get("content-length")
    if value is None:
        return 0
    try:
        return int(value)
    except ValueError:
        return None


async def _refuse(limit: int, path: str | None, scope: Scope, receive: Receive, send: Send) -> None:
    where = f"{scope['method']} {path}" if path else "a request without a body"
    message = f"the request body is larger than {limit} bytes, the limit of {where}"
    await error_response("too_large", message, headers={"Connection": "close"})(scope, receive, send)
