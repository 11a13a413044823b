"""/library: scan a folder of the server as a batch job, its results, a decision per photo, write back,
undo, exports; and the Library page. Parse, call ``app.library``, shape.

Every route but the page itself needs the key (``write_access``), reads included: a scan's results, its
thumbnails and its exports show the server's files (names, photos, places), which ``read_access`` (open
by default) would hand to anyone who can reach the port. The page tells no more than whether this server
scans folders at all."""

from __future__ import annotations

import threading
from pathlib import Path as FsPath
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response
from pydantic import BaseModel, Field

from app.api import security
from app.api.deps import Core, write_access
from app.api.errors import ApiError, error_responses
from app.engine.errors import GeolocError
from app.library.exports import FORMATS, MEDIA_TYPES
from app.library.jobs import FolderRefused, LibraryJobs, LibraryUnavailable, ScanBusy
from app.library.review import DecisionError
from app.library.scan import ScanOptions
from app.library.writeback import WriteBackError

router = APIRouter()
#: The Library view: its own page beside index.html, under the same Content-Security-Policy.
PAGE = FsPath(__file__).resolve().parents[2] / "web" / "static" / "library.html"
ScanId = Annotated[str, Path(pattern="^[0-9a-f]{16}$", description="a library's id (POST /library/scans)")]
PhotoId = Annotated[int, Path(ge=1, le=2**63 - 1)]


class ScanIn(BaseModel):
    folder: str = Field(max_length=4096, description="a folder under GEOLOC_LIBRARY_ROOT (absolute or relative)")
    time_prior: bool = True
    rerank: bool = False


class DecisionIn(BaseModel):
    action: Literal["accept", "move", "reject", "clear"]
    lat: float | None = None
    lon: float | None = None


class WriteIn(BaseModel):
    in_file: bool = Field(False, description="EXIF GPS in the photo itself; default: XMP sidecars")
    dry_run: bool = False


_MAKING = threading.Lock()


def jobs(request: Request, core: Core) -> LibraryJobs:
    """The server's library runner, made once (under a lock: two at once would run the same scan twice)
    over the served data dir at its first use; the app's shutdown closes it (its scans stop)."""
    state = request.app.state
    with _MAKING:
        if getattr(state, "library", None) is None:
            try:
                state.library = LibraryJobs.open(core.data_dir, state.settings.library_root)
            except LibraryUnavailable as e:  # a journal of another layout, damaged, not SQLite: said, not a 500
                raise ApiError(503, "not_ready", str(e)) from None
    return state.library


Jobs = Annotated[LibraryJobs, Depends(jobs)]


def _photo_out(rec) -> dict:
    """A journalled photo (``LibraryJobs.photo``) as the API shows it."""
    return {"id": rec.id, "kind": rec.kind, "decision": rec.decision, "accepted_lat": rec.lat,
            "accepted_lon": rec.lon, "written": rec.written, **rec.result}  # fmt: skip


def _scan(lib: LibraryJobs, sid: str) -> dict:
    got = lib.scan(sid)
    if got is None:
        raise ApiError(404, "not_found", f"no library scan {sid}")
    return got


#: Where the page is told whether this server scans folders (see ``library_page``).
SCANS_MARK = 'data-scans-folders="unknown"'


@router.get("/library", include_in_schema=False)
def library_page(request: Request) -> HTMLResponse:
    """The page, told whether this server scans folders: without GEOLOC_LIBRARY_ROOT every scan is refused,
    so the page says why instead of offering one. A yes or no is all a caller without the key learns (never
    the root: paths of the server are for key holders), and the page needs it before any key is typed."""
    scans = "yes" if request.app.state.settings.library_root is not None else "no"
    html = PAGE.read_text(encoding="utf-8").replace(SCANS_MARK, f'data-scans-folders="{scans}"', 1)
    return HTMLResponse(html, headers=security.PAGE_HEADERS)


@router.post(
    "/library/scans",
    status_code=202,
    responses=error_responses(401, 422, 503),
    dependencies=[Depends(write_access)],
    summary="Scan a folder: its GPS photos join the collection, the others are located (a batch job)",
)
def start_scan(body: ScanIn, core: Core, lib: Jobs) -> JSONResponse:
    try:
        folder = lib.folder(body.folder)
    except FolderRefused as e:
        raise ApiError(422, "invalid_request", str(e)) from None
    # One thread: a scan shares the server's cores with /locate, which must keep answering.
    try:
        sid = lib.start(core, folder, ScanOptions(workers=1, time_prior=body.time_prior, rerank=body.rerank))
    except ScanBusy as e:
        raise ApiError(503, "not_ready", str(e)) from None
    return JSONResponse({"id": sid, "state": "running"}, status_code=202, headers={"Location": f"/library/scans/{sid}"})


@router.get(
    "/library/scans/{sid}",
    responses=error_responses(401, 404, 503),
    dependencies=[Depends(write_access)],
    summary="A scan's state and every photo's suggestion, decision and write",
)
def get_scan(sid: ScanId, lib: Jobs) -> dict:
    scan = _scan(lib, sid)
    photos = [_photo_out(r) for r in lib.results(sid)]
    return {**scan, "photos": photos}


@router.get(
    "/library/scans/{sid}/photos/{photo_id}/thumbnail",
    response_class=Response,
    responses={200: {"content": {"image/jpeg": {}}}, **error_responses(401, 404, 503)},
    dependencies=[Depends(write_access)],
    summary="A thumbnail of a library photo (pixels only)",
)
def photo_thumbnail(request: Request, sid: ScanId, photo_id: PhotoId, lib: Jobs) -> Response:
    try:
        settings = request.app.state.settings
        data = lib.photo_thumbnail(sid, photo_id, settings.thumbnail_px, settings.image_limits())
    except (OSError, GeolocError):  # gone, a link, not an image (a library holds such files), too large
        raise ApiError(404, "image_missing", f"photo {photo_id} cannot be read any more") from None
    if data is None:
        raise ApiError(404, "not_found", f"no photo {photo_id} in library scan {sid}")
    # A private photo of the server's disk, fetched with the key: no shared cache may keep it.
    return Response(data, media_type="image/jpeg", headers={"Cache-Control": "private, no-store"})


@router.post(
    "/library/scans/{sid}/photos/{photo_id}/decision",
    responses=error_responses(401, 404, 422, 503),
    dependencies=[Depends(write_access)],
    summary="Accept a suggestion, move its pin (accept at lat/lon), reject it, or clear the decision",
)
def photo_decision(sid: ScanId, photo_id: PhotoId, body: DecisionIn, lib: Jobs) -> dict:
    _scan(lib, sid)
    if lib.photo(sid, photo_id) is None:
        raise ApiError(404, "not_found", f"no photo {photo_id} in library scan {sid}")
    try:
        return _photo_out(lib.decide(sid, photo_id, body.action, body.lat, body.lon))
    except DecisionError as e:
        raise ApiError(422, "invalid_request", str(e)) from None


@router.post(
    "/library/scans/{sid}/write",
    responses=error_responses(401, 404, 503),
    dependencies=[Depends(write_access)],
    summary="Write the accepted positions (XMP sidecars, or EXIF with in_file), or list them (dry_run)",
)
def write(sid: ScanId, body: WriteIn, lib: Jobs) -> dict:
    _scan(lib, sid)
    try:
        return lib.write_back(sid, body.in_file, body.dry_run)
    except (WriteBackError, ScanBusy) as e:
        raise ApiError(503, "not_ready", str(e)) from None


@router.post(
    "/library/scans/{sid}/undo",
    responses=error_responses(401, 404, 503),
    dependencies=[Depends(write_access)],
    summary="Undo every write of this library, newest first (a file changed since is skipped and listed)",
)
def undo_writes(sid: ScanId, lib: Jobs) -> dict:
    _scan(lib, sid)
    try:
        return lib.undo(sid)
    except ScanBusy as e:
        raise ApiError(503, "not_ready", str(e)) from None


@router.get(
    "/library/scans/{sid}/export",
    response_class=Response,
    responses=error_responses(401, 404, 422, 503),
    dependencies=[Depends(write_access)],
    summary="The accepted positions (or every suggestion, all=true) as GeoJSON, CSV or GPX",
)
def export(
    sid: ScanId,
    lib: Jobs,
    format: Annotated[Literal["geojson", "csv", "gpx"], Query(description=", ".join(FORMATS))] = "geojson",
    all: Annotated[bool, Query(description="every suggestion with its radius, not only the accepted")] = False,
) -> Response:
    _scan(lib, sid)
    text = lib.export(sid, format, all)
    name = f"library-{sid}.{format}"
    return Response(
        text, media_type=MEDIA_TYPES[format], headers={"Content-Disposition": f'attachment; filename="{name}"'}
    )
