"""The service's endpoints. Each handler validates, calls the engine or the store, and shapes JSON."""

from __future__ import annotations

import io
import json
import math
import secrets
import time
from pathlib import PurePosixPath
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, File, Form, Header, Path, Query, Request, UploadFile
from fastapi.responses import JSONResponse, Response
from PIL import Image, ImageOps
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from app.api.errors import ApiError, error_responses
from app.api.schemas import (
    AcceptedOut,
    CandidateOut,
    EstimateOut,
    HealthOut,
    JobOut,
    LocateOut,
    ReadyOut,
    ReferenceList,
    ReferenceOut,
)
from app.engine import rerank as rerank_mod
from app.engine.errors import InvalidPosition, NoGpsInImage
from app.engine.geo import haversine_m, valid_position
from app.engine.imageio import LoadedImage, load_image
from app.engine.locator import Locator
from app.store import sha256_of
from app.worker import LiveCollection

router = APIRouter()


# -- dependencies -------------------------------------------------------------------------------------
def live(request: Request) -> LiveCollection:
    state = request.app.state
    if state.live is None:
        raise ApiError(503, "not_ready", state.load_error or "the model, pipeline and index are still loading")
    return state.live


def _check_key(request: Request, key: str | None) -> None:
    """Every address alike, loopback included: the port may be forwarded or shared. None only under --no-auth."""
    expected = request.app.state.api_key
    if expected and not (key and secrets.compare_digest(key.encode(), expected.encode())):
        raise ApiError(401, "unauthorized", "this call needs a valid X-API-Key header")


def write_access(request: Request, x_api_key: Annotated[str | None, Header()] = None) -> None:
    _check_key(request, x_api_key)


def read_access(request: Request, x_api_key: Annotated[str | None, Header()] = None) -> None:
    if request.app.state.settings.protect_reads:
        _check_key(request, x_api_key)


Live = Annotated[LiveCollection, Depends(live)]
#: SQLite integers are 64-bit: a larger id is a 422, not an overflow deep in the store.
RefId = Annotated[int, Path(ge=1, le=2**63 - 1, description="reference id")]


def _read_upload(request: Request, upload: UploadFile) -> bytes:
    limit = request.app.state.settings.max_upload_bytes
    data = upload.file.read(limit + 1)
    if len(data) > limit:
        raise ApiError(413, "too_large", f"{upload.filename or 'the image'} is larger than {limit} bytes")
    return data


def _parse_bbox(text: str) -> tuple[float, float, float, float]:
    try:
        parts = [float(x) for x in text.split(",")]
    except ValueError:
        raise ApiError(422, "invalid_request", "bbox must be min_lon,min_lat,max_lon,max_lat (numbers)") from None
    if len(parts) != 4 or not all(math.isfinite(p) for p in parts):
        raise ApiError(422, "invalid_request", "bbox must be four finite numbers: min_lon,min_lat,max_lon,max_lat")
    min_lon, min_lat, max_lon, max_lat = parts
    if (
        not (valid_position(min_lat, min_lon) and valid_position(max_lat, max_lon))
        or min_lon > max_lon
        or (min_lat > max_lat)
    ):
        raise ApiError(422, "invalid_request", "bbox is out of range or inverted (min must not exceed max)")
    return min_lon, min_lat, max_lon, max_lat


def _region_ids(col: LiveCollection, lat, lon, radius_m, bbox) -> np.ndarray | None:
    if bbox is not None:
        if lat is not None or lon is not None or radius_m is not None:
            raise ApiError(422, "invalid_request", "give either bbox or lat+lon+radius_m, not both")
        return col.store.ids_in_bbox(_parse_bbox(bbox))
    given = [v is not None for v in (lat, lon, radius_m)]
    if not any(given):
        return None
    if not all(given):
        raise ApiError(422, "invalid_request", "a circular region needs lat, lon and radius_m together")
    if not valid_position(lat, lon):
        raise ApiError(422, "invalid_request", f"region centre {lat},{lon} is out of range")
    if not (math.isfinite(radius_m) and radius_m > 0):
        raise ApiError(422, "invalid_request", "radius_m must be a positive number of metres")
    dlat = radius_m / 111_320
    dlon = radius_m / (111_320 * max(math.cos(math.radians(lat)), 1e-6))
    ids = col.store.ids_in_bbox((lon - dlon, lat - dlat, lon + dlon, lat + dlat))
    if len(ids) == 0:
        return ids
    la, lo = col.store.positions(ids)
    return ids[haversine_m(lat, lon, la, lo) <= radius_m]


# -- /locate --------------------------------------------------------------------------------------------
@router.post(
    "/locate",
    response_model=LocateOut,
    responses=error_responses(400, 401, 413, 415, 422, 503),
    dependencies=[Depends(read_access)],
    summary="Where was this photo taken? Ranked GPS candidates and a fused estimate",
)
def locate(
    request: Request,
    col: Live,
    image: Annotated[UploadFile, File(description="the photo (JPEG, PNG, WebP or TIFF)")],
    top_k: Annotated[int, Form(ge=1, le=100)] = 10,
    mode: Annotated[str | None, Form(description="float, binary or two-stage; default: the best available")] = None,
    rerank: Annotated[bool, Form(description="geometric verification of the top candidates (slower)")] = False,
    lat: Annotated[float | None, Form(description="region centre (with lon and radius_m)")] = None,
    lon: Annotated[float | None, Form()] = None,
    radius_m: Annotated[float | None, Form()] = None,
    bbox: Annotated[str | None, Form(description="region as min_lon,min_lat,max_lon,max_lat")] = None,
    min_score: Annotated[float, Form(ge=0, le=1)] = 0.0,
) -> LocateOut:
    settings = request.app.state.settings
    metrics = request.app.state.metrics
    t0 = time.perf_counter()
    index = col.current()
    mode = index.check_mode(mode)
    allowed = _region_ids(col, lat, lon, radius_m, bbox)
    with request.app.state.extract_slots:
        t_start = time.perf_counter()
        data = _read_upload(request, image)
        img = load_image(data, settings.image_limits())
        decode_ms = (time.perf_counter() - t_start) * 1000
        features = col.pipeline.extract(img.rgb)
    queue_ms = (t_start - t0) * 1000
    with col.lock:
        res = Locator(col.pipeline, index, col.store.positions).locate_features(
            features, top_k=top_k, mode=mode, allowed=allowed
        )
        version = col.version
    timings = {"queue": queue_ms, "decode": decode_ms, **res.timings_ms}
    cands = [c for c in res.candidates if c.score >= min_score]
    inliers: dict[int, int] = {}
    if rerank and cands:
        t1 = time.perf_counter()
        q = rerank_mod.features_for_verification(img.rgb)
        for c in cands[:10]:
            path = col.store.image_path(c.reference_id)
            if path is not None and path.exists():
                ref = load_image(path.read_bytes(), settings.image_limits())
                inliers[c.reference_id] = rerank_mod.count_inliers(q, rerank_mod.features_for_verification(ref.rgb))
        cands.sort(key=lambda c: (-inliers.get(c.reference_id, -1), -c.score))
        timings["rerank"] = (time.perf_counter() - t1) * 1000
    timings["total"] = (time.perf_counter() - t0) * 1000
    for stage, ms in timings.items():
        metrics.stage.labels(stage).observe(ms / 1000)
    if settings.keep_queries:
        (col.store.data_dir / "queries").mkdir(exist_ok=True)
        (col.store.data_dir / "queries" / f"{sha256_of(data)}.{img.format.lower()}").write_bytes(data)

    e = res.estimate
    if allowed is not None and len(allowed) == 0:
        reason = "no references in the requested region"
    elif not cands:
        reason = "no candidate scored above min_score" if res.candidates else e.reason
    else:
        reason = e.reason
    estimate = (
        EstimateOut(lat=e.lat, lon=e.lon, radius_m=e.radius_m, confidence=e.confidence)
        if (e.confident and cands and reason is None)
        else None
    )
    out = []
    for c in cands:
        ref = col.store.get(c.reference_id)
        out.append(
            CandidateOut(
                reference_id=c.reference_id,
                lat=c.lat,
                lon=c.lon,
                score=round(c.score, 6),
                distance_m=float(haversine_m(estimate.lat, estimate.lon, c.lat, c.lon)) if estimate else None,
                label=ref.label if ref else None,
                captured_at=ref.captured_at if ref else None,
                heading=ref.heading if ref else None,
                inliers=inliers.get(c.reference_id) if rerank else None,
            )
        )
    return LocateOut(
        candidates=out,
        estimate=estimate,
        reason=reason,
        mode=res.mode,
        config=col.pipeline.config.name,
        features={"extracted": res.features_extracted, "kept": res.features_kept},
        timings_ms={k: round(v, 3) for k, v in timings.items()},
        index={"size": index.size, "version": version},
    )


# -- /references ----------------------------------------------------------------------------------------
def _position(meta: dict, img: LoadedImage, n: int) -> tuple[float, float]:
    lat, lon = meta.get("lat"), meta.get("lon")
    if lat is None and lon is None:
        if img.gps is None:
            raise NoGpsInImage(f"image {n}: no lat/lon given and no GPS position in its EXIF")
        return img.gps
    if lat is None or lon is None:
        raise InvalidPosition(f"image {n}: give both lat and lon, or neither (to use the EXIF GPS)")
    try:
        lat, lon = float(lat), float(lon)
    except (TypeError, ValueError):
        raise InvalidPosition(f"image {n}: lat and lon must be numbers") from None
    if not valid_position(lat, lon):
        raise InvalidPosition(f"image {n}: position {lat},{lon} is out of range (lat -90..90, lon -180..180)")
    return lat, lon


def _label_from(filename: str | None) -> str | None:
    if not filename:
        return None
    name = PurePosixPath(filename.replace("\\", "/")).name  # never a path: "../../x.jpg" -> "x.jpg"
    return name[:200] or None


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
    col: Live,
    image: Annotated[list[UploadFile], File(description="one or more images")],
    lat: Annotated[float | None, Form()] = None,
    lon: Annotated[float | None, Form()] = None,
    heading: Annotated[float | None, Form(ge=0, lt=360)] = None,
    captured_at: Annotated[str | None, Form(max_length=64)] = None,
    label: Annotated[str | None, Form(max_length=200)] = None,
    metadata: Annotated[str | None, Form(description="JSON list of {lat, lon, heading, captured_at, label}")] = None,
) -> JSONResponse:
    settings = request.app.state.settings
    if len(image) > settings.max_files_per_request:
        raise ApiError(
            413, "too_many_files", f"{len(image)} images in one request; the limit is {settings.max_files_per_request}"
        )
    if metadata is not None:
        try:
            metas = json.loads(metadata)
        except json.JSONDecodeError as e:
            raise ApiError(422, "invalid_request", f"metadata is not valid JSON: {e}") from None
        if not isinstance(metas, list) or not all(isinstance(m, dict) for m in metas) or len(metas) != len(image):
            raise ApiError(
                422, "invalid_request", f"metadata must be a JSON list of {len(image)} objects, one per image in order"
            )
    else:
        metas = [
            {"lat": lat, "lon": lon, "heading": heading, "captured_at": captured_at, "label": label} for _ in image
        ]
    prepared = []
    for n, (upload, meta) in enumerate(zip(image, metas, strict=True)):
        data = _read_upload(request, upload)
        img = load_image(data, settings.image_limits())  # validates everything before anything is stored
        plat, plon = _position(meta, img, n)
        hd = meta.get("heading")
        if hd is not None and not (isinstance(hd, int | float) and 0 <= hd < 360):
            raise ApiError(422, "invalid_request", f"image {n}: heading must be a number in [0, 360)")
        prepared.append((data, img, plat, plon, meta, upload.filename))
    ids, dups = [], []
    for data, img, plat, plon, meta, filename in prepared:
        ref_id, created = col.store.add(
            data,
            img.format.lower(),
            plat,
            plon,
            None,
            None,
            heading=meta.get("heading"),
            captured_at=str(meta["captured_at"])[:64] if meta.get("captured_at") else img.captured_at,
            label=str(meta["label"])[:200] if meta.get("label") else _label_from(filename),
            source="api",
            pending=True,
        )
        ids.append(ref_id)
        dups.append(not created)
    job_id = col.store.create_job(list(zip(ids, dups, strict=True)))
    worker = request.app.state.worker
    if worker is not None:
        worker.wake.set()
    body = AcceptedOut(job_id=job_id, reference_ids=ids, duplicates=dups)
    return JSONResponse(body.model_dump(), status_code=202, headers={"Location": f"/jobs/{job_id}"})


@router.get(
    "/jobs/{job_id}",
    response_model=JobOut,
    responses=error_responses(401, 404, 503),
    dependencies=[Depends(read_access)],
    summary="Progress of an ingestion job",
)
def get_job(job_id: str, col: Live) -> JobOut:
    job = col.store.job(job_id)
    if job is None:
        raise ApiError(404, "not_found", f"no job {job_id}")
    return JobOut(**job)


def _ref_out(ref) -> ReferenceOut:
    return ReferenceOut(**ref.as_dict())


@router.get(
    "/references",
    response_model=ReferenceList,
    responses=error_responses(401, 422, 503),
    dependencies=[Depends(read_access)],
    summary="List references, paged, optionally within a bbox",
)
def list_references(
    col: Live,
    offset: Annotated[int, Query(ge=0, le=2**63 - 1)] = 0,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    bbox: Annotated[str | None, Query(description="min_lon,min_lat,max_lon,max_lat")] = None,
) -> ReferenceList:
    refs, total = col.store.list(offset, limit, _parse_bbox(bbox) if bbox else None)
    return ReferenceList(items=[_ref_out(r) for r in refs], total=total, offset=offset, limit=limit)


@router.get(
    "/references/{ref_id}",
    response_model=ReferenceOut,
    responses=error_responses(401, 404, 422, 503),
    dependencies=[Depends(read_access)],
    summary="One reference's metadata and status",
)
def get_reference(ref_id: RefId, col: Live) -> ReferenceOut:
    ref = col.store.get(ref_id)
    if ref is None:
        raise ApiError(404, "not_found", f"no reference {ref_id}")
    return _ref_out(ref)


@router.get(
    "/references/{ref_id}/image",
    responses={
        200: {"content": {"image/jpeg": {}}, "description": "a JPEG thumbnail without EXIF"},
        **error_responses(401, 404, 422, 503),
    },
    response_class=Response,
    dependencies=[Depends(read_access)],
    summary="A thumbnail of the reference image (no EXIF)",
)
def reference_image(request: Request, ref_id: RefId, col: Live) -> Response:
    path = col.store.image_path(ref_id)
    if path is None or not path.exists():
        raise ApiError(404, "not_found", f"no reference {ref_id}")
    size = request.app.state.settings.thumbnail_px
    with Image.open(path) as im:
        im.draft("RGB", (size * 2, size * 2))
        im = ImageOps.exif_transpose(im).convert("RGB")
        im.thumbnail((size, size))
        buf = io.BytesIO()
        im.save(buf, "JPEG", quality=85)  # a new file: no EXIF, no GPS block
    return Response(buf.getvalue(), media_type="image/jpeg", headers={"Cache-Control": "max-age=3600"})


@router.delete(
    "/references/{ref_id}",
    responses=error_responses(401, 404, 422, 503),
    dependencies=[Depends(write_access)],
    summary="Delete a reference: image, codes and metadata",
)
def delete_reference(ref_id: RefId, col: Live) -> dict:
    if not col.delete(ref_id):
        raise ApiError(404, "not_found", f"no reference {ref_id}")
    return {"deleted": ref_id}


# -- operations -----------------------------------------------------------------------------------------
@router.get("/health", response_model=HealthOut, summary="The process is alive")
def health() -> HealthOut:
    return HealthOut(status="ok")


@router.get(
    "/ready",
    response_model=ReadyOut,
    responses=error_responses(503),
    summary="Model, pipeline and index are loaded (503 until then)",
)
def ready(request: Request):
    state = request.app.state
    if state.live is None:
        return JSONResponse({"error": "not_ready", "message": state.load_error or "loading"}, status_code=503)
    col = state.live
    index = col.current()
    return ReadyOut(
        status="ready",
        config=col.pipeline.config.name,
        index_size=index.size,
        version=col.version,
        worker="in-process" if state.worker is not None else "external",
    )


@router.get("/metrics", response_class=Response, summary="Prometheus metrics")
def metrics(request: Request) -> Response:
    state = request.app.state
    m = state.metrics
    if state.live is not None:
        index = state.live.current()
        if index.float is not None:
            m.index_size.labels("float").set(index.float.ntotal)
        if index.binary is not None:
            m.index_size.labels("binary").set(index.binary.ntotal)
        m.queue_depth.set(state.live.store.count("pending"))
    return Response(generate_latest(m.registry), media_type=CONTENT_TYPE_LATEST)
