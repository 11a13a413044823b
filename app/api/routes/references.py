"""/references (add, list, get, thumbnail, edit, delete) and /jobs (an upload's progress): parse, call the
service, shape."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, Query, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import TypeAdapter, ValidationError

from app.api.deps import Core, RefId, parse_bbox, read_access, read_upload, write_access
from app.api.errors import ApiError, error_responses
from app.api.schemas import AcceptedOut, JobOut, ReferenceList, ReferenceOut, ReferencePatch
from app.domain import ReferenceFields, Region, Upload
from app.text import CAPTURED_AT_MAX, LABEL_MAX

router = APIRouter()


#: ``metadata`` is bounded before it is parsed: a label of 200 characters written as JSON escapes, a capture
#: time and three numbers fit in well under this per image.
METADATA_CHARS_PER_IMAGE = 4096
_METADATA = TypeAdapter(list[ReferenceFields])


def _validated(fields: dict, loc: tuple) -> ReferenceFields:
    """The form fields through the same model as ``metadata`` and PATCH (FastAPI has parsed the numbers)."""
    try:
        return ReferenceFields.model_validate({k: v for k, v in fields.items() if v is not None})
    except ValidationError as e:
        raise RequestValidationError([{**err, "loc": (*loc, *err["loc"])} for err in e.errors()]) from None


def _parse_metadata(text: str, n_images: int) -> list[ReferenceFields]:
    """``metadata`` as one model per image. pydantic's JSON parser (not ``json``) keeps a depth limit and
    turns a number too large for a float into a validation error: nothing here can raise but a 422."""
    limit = METADATA_CHARS_PER_IMAGE * max(n_images, 1)
    if len(text) > limit:
        raise ApiError(
            422, "invalid_request", f"metadata has {len(text)} characters; the limit is {limit} for {n_images} images"
        )
    try:
        metas = _METADATA.validate_json(text)
    except ValidationError as e:
        broken = [err for err in e.errors() if err["type"] == "json_invalid"]
        if broken:
            raise ApiError(422, "invalid_request", f"metadata is not valid JSON: {broken[0]['msg']}") from None
        raise RequestValidationError([{**err, "loc": ("metadata", *err["loc"])} for err in e.errors()]) from None
    if len(metas) != n_images:
        raise ApiError(
            422, "invalid_request", f"metadata must be a JSON list of {n_images} objects, one per image in order"
        )
    return metas


@router.post(
    "/references",
    status_code=202,
    response_model=AcceptedOut,
    responses=error_responses(400, 401, 413, 415, 422, 503),
    dependencies=[Depends(write_access)],
    summary="Add geotagged reference images (encoded by the ingestion worker)",
)
def add_references(
    request: Request,
    core: Core,
    image: Annotated[list[UploadFile], File(description="one or more images")],
    lat: Annotated[float | None, Form()] = None,
    lon: Annotated[float | None, Form()] = None,
    heading: Annotated[float | None, Form(description="degrees in [0, 360)")] = None,
    captured_at: Annotated[str | None, Form(description=f"at most {CAPTURED_AT_MAX} characters")] = None,
    label: Annotated[str | None, Form(description=f"at most {LABEL_MAX} characters")] = None,
    metadata: Annotated[
        str | None,
        Form(
            description="JSON list of {lat, lon, heading, captured_at, label}, one per image in order "
            f"(at most {METADATA_CHARS_PER_IMAGE} characters per image); replaces the other fields"
        ),
    ] = None,
) -> JSONResponse:
    """Text fields refuse control and bidirectional characters (U+0000-U+001F, U+202E...), in ``metadata``
    and in a file name used as the label alike."""
    settings = request.app.state.settings
    if len(image) > settings.max_files_per_request:
        raise ApiError(
            413, "too_many_files", f"{len(image)} images in one request; the limit is {settings.max_files_per_request}"
        )
    if metadata is not None:
        metas = _parse_metadata(metadata, len(image))
    else:
        given = {"lat": lat, "lon": lon, "heading": heading, "captured_at": captured_at, "label": label}
        metas = [_validated(given, ())] * len(image)
    uploads = [
        Upload(read_upload(request, upload), upload.filename, **meta.model_dump())
        for upload, meta in zip(image, metas, strict=True)
    ]
    accepted = core.accept(uploads)
    worker = request.app.state.worker
    if worker is not None:
        worker.wake.set()
    body = AcceptedOut(
        job_id=accepted.job_id,
        reference_ids=accepted.reference_ids,
        duplicates=accepted.duplicates,
        notes=accepted.notes,
    )
    return JSONResponse(body.model_dump(), status_code=202, headers={"Location": f"/jobs/{accepted.job_id}"})


@router.get(
    "/jobs/{job_id}",
    response_model=JobOut,
    responses=error_responses(401, 404, 503),
    dependencies=[Depends(read_access)],
    summary="Progress of an ingestion job",
)
def get_job(job_id: str, core: Core) -> JobOut:
    job = core.job(job_id)
    if job is None:
        raise ApiError(404, "not_found", f"no job {job_id}")
    return JobOut.model_validate(job, from_attributes=True)


def _ref_out(ref) -> ReferenceOut:
    return ReferenceOut.model_validate(ref, from_attributes=True)


@router.get(
    "/references",
    response_model=ReferenceList,
    responses=error_responses(401, 422, 503),
    dependencies=[Depends(read_access)],
    summary="List references, paged, optionally within a bbox",
)
def list_references(
    core: Core,
    offset: Annotated[int, Query(ge=0, le=2**63 - 1, description="page by position (counts every row)")] = 0,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    bbox: Annotated[str | None, Query(description="min_lon,min_lat,max_lon,max_lat")] = None,
    after: Annotated[
        int | None, Query(ge=0, le=2**63 - 1, description="page by id: the references with ids above this")
    ] = None,
    before: Annotated[
        int | None, Query(ge=0, le=2**63 - 1, description="page by id: the references with ids below this")
    ] = None,
    total: Annotated[bool, Query(description="on id pages: count every matching row too (O(rows))")] = False,
) -> ReferenceList:
    box = Region(bbox=parse_bbox(bbox)).bbox if bbox else None
    if after is None and before is None:
        refs, count = core.list(offset, limit, box)
        return ReferenceList(
            items=[_ref_out(r) for r in refs],
            total=count,
            offset=offset,
            limit=limit,
            next_after=refs[-1].id if refs and offset + len(refs) < count else None,
            prev_before=refs[0].id if refs and offset > 0 else None,
        )
    if after is not None and before is not None:
        raise ApiError(422, "invalid_request", "give after or before, not both")
    if offset:
        raise ApiError(422, "invalid_request", "offset pages by position, after/before by id: give one of them")
    page = core.page(after, before, limit, box)
    return ReferenceList(
        items=[_ref_out(r) for r in page.items],
        total=core.count_in(box) if total else None,
        offset=None,
        limit=limit,
        next_after=page.next_after,
        prev_before=page.prev_before,
    )


@router.get(
    "/references/{ref_id}",
    response_model=ReferenceOut,
    responses=error_responses(401, 404, 422, 503),
    dependencies=[Depends(read_access)],
    summary="One reference's metadata and status",
)
def get_reference(ref_id: RefId, core: Core) -> ReferenceOut:
    ref = core.get(ref_id)
    if ref is None:
        raise ApiError(404, "not_found", f"no reference {ref_id}")
    return _ref_out(ref)


@router.get(
    "/references/{ref_id}/image",
    responses={
        200: {"content": {"image/jpeg": {}}, "description": "a JPEG thumbnail: pixels only (JFIF)"},
        **error_responses(401, 404, 422, 503),
    },
    response_class=Response,
    dependencies=[Depends(read_access)],
    summary="A thumbnail of the reference image (pixels only: no EXIF, XMP, ICC or comment)",
)
def reference_image(request: Request, ref_id: RefId, core: Core) -> Response:
    try:
        data = core.thumbnail(ref_id)
    except FileNotFoundError:
        raise ApiError(
            404, "image_missing", f"reference {ref_id} exists but its stored image is missing (see `geoloc check`)"
        ) from None
    if data is None:
        raise ApiError(404, "not_found", f"no reference {ref_id}")
    return Response(data, media_type="image/jpeg", headers={"Cache-Control": "max-age=3600"})


@router.patch(
    "/references/{ref_id}",
    response_model=ReferenceOut,
    responses=error_responses(401, 404, 422, 503),
    dependencies=[Depends(write_access)],
    summary="Edit a reference's metadata (position, heading, label, capture time)",
)
def patch_reference(ref_id: RefId, patch: ReferencePatch, core: Core) -> ReferenceOut:
    ref = core.update(ref_id, patch)
    if ref is None:
        raise ApiError(404, "not_found", f"no reference {ref_id}")
    return _ref_out(ref)


@router.delete(
    "/references/{ref_id}",
    responses=error_responses(401, 404, 422, 503),
    dependencies=[Depends(write_access)],
    summary="Delete a reference: image, codes and metadata",
)
def delete_reference(ref_id: RefId, core: Core) -> dict:
    """The row and its codes are gone when this answers 200; ``image_removal`` says whether the image file is
    too ("done") or could not be removed yet ("queued": it is removed by the writer process's retries or by
    ``geoloc check --repair``, never left unowned)."""
    outcome = core.delete(ref_id)
    if outcome is None:
        raise ApiError(404, "not_found", f"no reference {ref_id}")
    return {"deleted": ref_id, "image_removal": "done" if outcome == "removed" else "queued"}
