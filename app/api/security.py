"""Response headers that contain a slip in the page: should user text ever reach the page as HTML again
(a label in the map tooltip once ran as script and sent the API key away), the browser still refuses to
run it, to send data elsewhere, or to show the page inside another site's frame.

The page (index.html, app.js, the vendored Leaflet) has no inline script, style or handler, so its policy
needs no 'unsafe-*'. /docs is Swagger UI, started by an inline script FastAPI writes: it shows no user
text, and gets only the framing and sniffing rules."""

from __future__ import annotations

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

#: Map tiles are the only other host the page uses, for images only (see makeMap in app.js). ``blob:`` is
#: the preview of the photo being located; ``data:`` is the empty GIF Leaflet puts in a tile it drops (an
#: image never runs script).
TILES = "https://tile.openstreetmap.org"

PAGE_POLICY = "; ".join(
    [
        "default-src 'self'",
        "script-src 'self'",
        "style-src 'self'",
        f"img-src 'self' data: blob: {TILES}",
        "connect-src 'self'",
        "object-src 'none'",
        "base-uri 'none'",
        "form-action 'self'",
        "frame-ancestors 'none'",
    ]
)

_NOT_FRAMED = {"X-Content-Type-Options": "nosniff", "X-Frame-Options": "DENY"}

#: For ``/``.
PAGE_HEADERS = {"Content-Security-Policy": PAGE_POLICY, **_NOT_FRAMED}
#: For ``/docs``.
DOCS_HEADERS = {"Content-Security-Policy": "frame-ancestors 'none'", **_NOT_FRAMED}


class HtmlPolicy:
    """Every HTML answer gets the page's policy unless it set its own (``/docs``), and every answer the
    framing and sniffing rules. Why a middleware and not headers per route: ``/static/index.html`` served the
    working page (where the key is typed) through StaticFiles with none of them, so it could be framed;
    any route or mount that serves HTML now gets them."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_policy(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in _NOT_FRAMED.items():
                    headers.setdefault(name, value)
                if headers.get("content-type", "").startswith("text/html"):
                    headers.setdefault("Content-Security-Policy", PAGE_POLICY)
            await send(message)

        await self.app(scope, receive, with_policy)
