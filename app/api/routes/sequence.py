"""POST /locate/sequence: several photos (a walk, a drive, a burst), located as one path. Parse
the form, call ``locate_sequence`` (the whole use case), shape the answers."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, File, Form, Request, UploadFile

from app.api.deps import Core, read_access, read_upload
from app.api.errors import error_responses
from app.api.routes.locate import region_of
from app.api.schemas import SequenceOut
from app.domain import LocateOptions
from app.engine.sequence import DEFAULT_SPEED_MPS, DEFAULT_STEP_M, Motion
from app.usecases.sequence import locate_sequence

router = APIRouter()


def _reader(request: Request, upload: UploadFile):
    """A function that reads one uploaded image from its start (it may be read twice: EXIF time, then pixels)."""

    def read() -> bytes:
        upload.file.seek(0)
        return read_upload(request, upload)

    return read


@router.post(
    "/locate/sequence",
    response_model=SequenceOut,
    responses=error_responses(400, 401, 413, 415, 422, 503),
    dependencies=[Depends(read_access)],
    summary="Where were these photos taken? Several photos, located as one path in the order taken",
)
def locate_sequence_route(
    request: Request,
    core: Core,
    image: Annotated[
        list[UploadFile],
        File(
            description="the photos in the order they were taken (any order with order=taken), one `image` field each"
        ),
    ],
    taken_at: Annotated[
        list[str] | None,
        Form(
            description="one ISO 8601 capture time per image, in the same order (e.g. 2024-09-23T16:08:20-04:00); "
            "none: each photo's EXIF DateTimeOriginal, else their order alone"
        ),
    ] = None,
    order: Annotated[
        Literal["sent", "taken"],
        Form(
            description="sent: the images are in the order they were taken (times that go backwards are refused); "
            "taken: in any order, located in the order of their times (taken_at, else EXIF) where every image has "
            "one; `images` in the answer says which image each answer is"
        ),
    ] = "sent",
    max_speed_mps: Annotated[
        float, Form(gt=0, le=100, description="the fastest the photographer moves, where the photos have times")
    ] = DEFAULT_SPEED_MPS,
    max_step_m: Annotated[
        float, Form(gt=0, le=100_000, description="the farthest apart two consecutive photos are, without times")
    ] = DEFAULT_STEP_M,
    top_k: Annotated[int, Form(ge=1, le=100)] = 10,
    mode: Annotated[str | None, Form(description="float, binary or two-stage; default: the best available")] = None,
    rerank: Annotated[bool | None, Form(description="geometric verification, as /locate's")] = None,
    lat: Annotated[float | None, Form(description="region centre (with lon and radius_m)")] = None,
    lon: Annotated[float | None, Form()] = None,
    radius_m: Annotated[float | None, Form()] = None,
    bbox: Annotated[str | None, Form(description="region as min_lon,min_lat,max_lon,max_lat")] = None,
    min_score: Annotated[float, Form(ge=0, le=1)] = 0.0,
) -> SequenceOut:
    options = LocateOptions(
        top_k=top_k, mode=mode, rerank=rerank, region=region_of(lat, lon, radius_m, bbox), min_score=min_score
    )
    result = locate_sequence(
        core,
        [_reader(request, u) for u in image],
        options,
        Motion(speed_mps=max_speed_mps, step_m=max_step_m),
        taken_at,
        request.app.state.settings.max_sequence_images,
        by_time=order == "taken",
    )
    return SequenceOut.of(result)
