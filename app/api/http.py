"""uvicorn's HTTP/1.1 protocol with a bound on how long a request's line and headers may take to arrive.

Why: uvicorn bounds an idle keep-alive connection (``timeout_keep_alive``) but not a request whose headers
never finish: 200 sockets that sent half a header line were held until the client went away (issue 30), a
slow-loris that needs no key. Each connection here must deliver a request's line and headers within
``GEOLOC_HEADER_TIMEOUT_SECONDS`` of the connection opening or of the previous response's end; it is
closed otherwise. The body is bounded elsewhere (app/api/limits.py), and a proxy in front (nginx's
``client_header_timeout``) may bound it again."""

from __future__ import annotations

import asyncio

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol


class BoundedHeadersProtocol(H11Protocol):
    """``H11Protocol`` plus the header deadline; ``header_timeout`` is set by ``bounded_headers``."""

    header_timeout: float = 10.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_header_deadline()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._arm_header_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_header_deadline()
        super().connection_lost(exc)

    def _arm_header_deadline(self) -> None:
        self._cancel_header_deadline()
        self._header_deadline = self.loop.call_later(self.header_timeout, self._header_deadline_passed)

    def _cancel_header_deadline(self) -> None:
        handle = getattr(self, "_header_deadline", None)
        if handle is not None:
            handle.cancel()
            self._header_deadline = None

    def _header_deadline_passed(self) -> None:
        """Close the connection if the request's headers are still not all in (the client is still IDLE to
        h11: its request line and headers have not completed)."""
        self._header_deadline = None
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.transport.close()


def bounded_headers(timeout: float) -> type[BoundedHeadersProtocol]:
    """The protocol class for ``uvicorn.run(http=...)`` with this deadline in seconds."""
    return type("BoundedHeaders", (BoundedHeadersProtocol,), {"header_timeout": float(timeout)})
