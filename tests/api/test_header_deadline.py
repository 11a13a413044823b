"""The header deadline of app/api/http.py on both of uvicorn's parsers, each in a real uvicorn server (in a
thread of the test) around a small ASGI app: unfinished headers are dropped, a slow answer is never cut,
and a request answered before its body was read (a 401 or 413 of app/api/limits.py) does not leave the
next request's headers unbounded."""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import pytest
import uvicorn

from app.api.http import BoundedH11, bounded_headers, httptools_protocol

DEADLINE_S = 1.0


async def slow_app(scope, receive, send):
    """/slow answers after 2.5 s (longer than the deadline); /early answers before reading its body."""
    if scope["type"] != "http":
        return
    if scope["path"] == "/slow":
        await asyncio.sleep(2.5)
    elif scope["path"] != "/early":
        while (await receive()).get("more_body"):
            pass
    await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"2")]})
    await send({"type": "http.response.body", "body": b"ok"})


@pytest.fixture(params=["h11", "httptools"])
def server(request):
    base = BoundedH11 if request.param == "h11" else httptools_protocol()
    if base is None:
        pytest.fail("httptools is not installed (uvicorn[standard] brings it)")
    protocol = type("P", (base,), {"header_timeout": DEADLINE_S})
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    config = uvicorn.Config(slow_app, http=protocol, log_level="warning", lifespan="off")
    srv = uvicorn.Server(config)
    thread = threading.Thread(target=srv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    while not srv.started:
        time.sleep(0.05)
    yield sock.getsockname()[1]
    srv.should_exit = True
    thread.join(10)


def _connect(port: int) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=10)


def _closed(sock: socket.socket) -> bool:
    try:
        return sock.recv(1024) == b""
    except ConnectionResetError:
        return True


def test_unfinished_headers_are_dropped_and_slow_answers_are_not(server):
    half = _connect(server)
    half.sendall(b"GET /x HTTP/1.1\r\nHost: x\r\nX-Slow: ")
    silent = _connect(server)
    slow = _connect(server)
    slow.sendall(b"GET /slow HTTP/1.1\r\nHost: x\r\n\r\n")
    time.sleep(DEADLINE_S + 1.0)
    assert _closed(half) and _closed(silent)
    assert slow.recv(1024).startswith(b"HTTP/1.1 200")  # answered after 2.5 s: the deadline did not cut it
    # On the kept-alive connection the next request's headers are bounded again.
    slow.sendall(b"GET /x HTTP/1.1\r\nHost: x\r\n")
    time.sleep(DEADLINE_S + 1.0)
    assert _closed(slow)


def test_an_answer_before_the_body_leaves_no_unbounded_headers(server):
    sock = _connect(server)
    sock.sendall(b"POST /early HTTP/1.1\r\nHost: x\r\nContent-Length: 10\r\n\r\n12345")
    assert sock.recv(1024).startswith(b"HTTP/1.1 200")
    sock.sendall(b"67890")  # the rest of the body, then only half of the next request's headers
    sock.sendall(b"GET /x HTTP/1.1\r\nHost: x\r\n")
    time.sleep(DEADLINE_S + 1.5)
    assert _closed(sock)


def test_the_serve_command_keeps_the_parser_uvicorn_would_pick():
    """httptools is installed with uvicorn[standard]: `geoloc serve` keeps it (``http="auto"`` did)."""
    assert issubclass(bounded_headers(3), httptools_protocol())
    assert bounded_headers(3).header_timeout == 3.0
