"""What the routes depend on: the loaded service, who may call what, and the shared parameter types.

Access: one key check, used by the routes' dependencies and, before any body is read, by the body-limit
middleware (app/api/limits.py), which calls the same dependency functions."""

from __future__ import annotations

import math
import secrets
from typing import Annotated

from fastapi import Depends, Header, Path, Request, UploadFile
from starlette.requests import HTTPConnection

from app.api.errors import ApiError
from app.usecases.service import GeolocService


# -- the service ----------------------------------------------------------------------------------------
def service(request: Request) -> GeolocService:
    state = request.app.state
    if state.service is None:
        raise ApiError(503, "not_ready", state.not_ready or "the model, pipeline and index are still loading")
    return state.service


Core = Annotated[GeolocService, Depends(service)]
#: SQLite integers are 64-bit: a larger id is a 422, not an overflow deep in the store.
RefId = Annotated[int, Path(ge=1, le=2**63 - 1, description="reference id")]


# -- access ---------------------------------------------------------------------------------------------
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


# -- parsing shared by the routes -----------------------------------------------------------------------
def read_upload(request: Request, upload: UploadFile) -> bytes:
    """One uploaded file, refused (413) past the upload limit without reading more than one byte over it."""
    limit = request.app.state.settings.max_upload_bytes
    data = upload.file.read(limit + 1)
    if len(data) > limit:
        raise ApiError(413, "too_large", f"{upload.filename or 'the image'} is larger than {limit} bytes")
    return data


def parse_bbox(text: str) -> tuple[float, float, float, float]:
    try:
        parts = [float(x) for x in text.split(",")]
    except ValueError:
        raise ApiError(422, "invalid_request", "bbox must be min_lon,min_lat,max_lon,max_lat (numbers)") from None
    if len(parts) != 4 or not all(math.isfinite(p) for p in parts):
        raise ApiError(422, "invalid_request", "bbox must be four finite numbers: min_lon,min_lat,max_lon,max_lat")
    min_lon, min_lat, max_lon, max_lat = parts
    return min_lon, min_lat, max_lon, max_lat
