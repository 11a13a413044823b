"""Who may call what: one key check, used by the routes' dependencies and, before any body is read, by the
body-limit middleware (app/api/limits.py), which calls the same dependency functions."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Header
from starlette.requests import HTTPConnection

from app.api.errors import ApiError


def check_key(conn: HTTPConnection, key: str | None) -> None:
    """Every address alike, loopback included: the port may be forwarded or shared. None only under --no-auth."""
    expected = conn.app.state.api_key
    if expected and not (key and secrets.compare_digest(key.encode(), expected.encode())):
        raise ApiError(401, "unauthorized", "this call needs a valid X-API-Key header")


def write_access(request: HTTPConnection, x_api_key: Annotated[str | None, Header()] = None) -> None:
    check_key(request, x_api_key)


def read_access(request: HTTPConnection, x_api_key: Annotated[str | None, Header()] = None) -> None:
    if request.app.state.settings.protect_reads:
        check_key(request, x_api_key)


#: The dependencies that decide access; the middleware runs those a route declares.
ACCESS_CHECKS = (write_access, read_access)
