"""uvicorn's HTTP/1.1 protocols with a bound on how long a request's line and headers may take to arrive.

Why: uvicorn bounds an idle keep-alive connection (``timeout_keep_alive``) but not a request whose headers
never finish: sockets that sent half a header line were held until the client went away, a
slow-loris that needs no key. Here a connection must deliver each request's line and headers within
``GEOLOC_HEADER_TIMEOUT_SECONDS`` of the moment the server waits for them (the connection opened, or the
previous request was read and answered); it is closed otherwise. A request being answered is never cut:
the deadline runs only while the server waits for headers. The body is bounded elsewhere
(app/api/limits.py), and a proxy in front (nginx's ``client_header_timeout``) may bound it again.

Both of uvicorn's parsers get it, and ``bounded_headers`` picks the one uvicorn's ``http="auto"`` would
(httptools when it is installed, as it is with uvicorn[standard]; h11 otherwise), so the parser in use does
not change."""

from __future__ import annotations

import asyncio
import functools

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol


class HeaderDeadline:
    """The deadline's state, mixed into a uvicorn protocol before it (the protocol provides ``loop`` and
    ``transport``, and the connection callbacks this calls on)."""

    header_timeout: float = 10.0
    _deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:
        super().connection_made(transport)  # type: ignore[misc]
        self._arm()  # a new connection: the server waits for its first request's headers

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)  # type: ignore[misc]

    def _arm(self) -> None:
        """The server now waits for a request's headers: they must all be in within ``header_timeout``."""
        self._disarm()
        self._deadline = self.loop.call_later(self.header_timeout, self._expired)  # type: ignore[attr-defined]

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expired(self) -> None:
        self._deadline = None
        transport = self.transport  # type: ignore[attr-defined]
        if not transport.is_closing():
            transport.close()


class BoundedH11(HeaderDeadline, H11Protocol):
    """h11: it waits for headers exactly while the client's side is IDLE (h11 starts a new cycle only once
    both sides of the previous one are done)."""

    def handle_events(self) -> None:
        super().handle_events()
        self._follow()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._follow()

    def _follow(self) -> None:
        if self.conn.their_state is not h11.IDLE:
            self._disarm()  # its headers are in: the request is read or answered now
        elif self._deadline is None and not self.transport.is_closing():
            self._arm()


@functools.cache
def httptools_protocol() -> type | None:
    """``HttpToolsProtocol`` with the deadline; None when httptools is not installed (made once)."""
    try:
        from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
    except ImportError:  # httptools is not installed
        return None

    class BoundedHttpTools(HeaderDeadline, HttpToolsProtocol):
        """httptools: it waits for headers from the connection's start, and again once a request has been
        both read whole and answered; ``on_headers_complete`` ends the wait."""

        _read = True  # the last request was read whole (none yet: as if so)
        _answered = True

        def on_message_begin(self) -> None:
            self._read = False
            super().on_message_begin()

        def on_headers_complete(self) -> None:
            self._disarm()
            self._answered = False
            super().on_headers_complete()

        def on_message_complete(self) -> None:
            self._read = True
            super().on_message_complete()
            self._follow()

        def on_response_complete(self) -> None:
            self._answered = True
            super().on_response_complete()
            self._follow()

        def _follow(self) -> None:
            if self._read and self._answered and self._deadline is None and not self.transport.is_closing():
                self._arm()

    return BoundedHttpTools


def bounded_headers(timeout: float) -> type:
    """The protocol class for ``uvicorn.run(http=...)`` with this deadline in seconds: httptools' when it
    is installed (what ``http="auto"`` picks), else h11's."""
    base = httptools_protocol() or BoundedH11
    return type(f"{base.__name__}Deadline", (base,), {"header_timeout": float(timeout)})
