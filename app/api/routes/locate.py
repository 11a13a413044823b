"""POST /locate: parse the form, call ``GeolocService.locate`` (the whole use case), shape the answer."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, Request, UploadFile

from app.api.deps import Core, parse_bbox, read_access, read_upload
from app.api.errors import error_responses
from app.api.schemas import LocateOut
from app.domain import LocateOptions, Region

router = APIRouter()


def region_of(lat, lon, radius_m, bbox) -> Region | None:
    if bbox is not None:
        return Region(lat=lat, lon=lon, radius_m=radius_m, bbox=parse_bbox(bbox))
    if lat is None and lon is None and radius_m is None:
        return None
    return Region(lat=lat, lon=lon, radius_m=radius_m)


@router.post(
    "/locate",
    response_model=LocateOut,
    responses=error_responses(400, 401, 413, 415, 422, 503),
    dependencies=[Depends(read_access)],
    summary="Where was this photo taken? Ranked GPS candidates and a fused estimate",
)
def locate(
    request: Request,
    core: Core,
    image: Annotated[UploadFile, File(description="the photo (JPEG, PNG, WebP or TIFF)")],
    top_k: Annotated[int, Form(ge=1, le=100)] = 10,
    mode: Annotated[str | None, Form(description="float, binary or two-stage; default: the best available")] = None,
    rerank: Annotated[
        bool | None,
        Form(
            description="geometric verification of the top candidates; default: on for a configuration that "
            "stores local features, off (slower, re-extracting) otherwise"
        ),
    ] = None,
    lat: Annotated[float | None, Form(description="region centre (with lon and radius_m)")] = None,
    lon: Annotated[float | None, Form()] = None,
    radius_m: Annotated[float | None, Form()] = None,
    bbox: Annotated[str | None, Form(description="region as min_lon,min_lat,max_lon,max_lat")] = None,
    min_score: Annotated[float, Form(ge=0, le=1)] = 0.0,
) -> LocateOut:
    options = LocateOptions(
        top_k=top_k, mode=mode, rerank=rerank, region=region_of(lat, lon, radius_m, bbox), min_score=min_score
    )
    answer = core.locate(lambda: read_upload(request, image), options)
    stage = request.app.state.metrics.stage
    for name, ms in answer.timings_ms.items():
        stage.labels(name).observe(ms / 1000)
    return LocateOut.of(answer)
