"""Operations: /health (alive), /ready (loaded, 503 until then), /metrics (Prometheus).

With ``GEOLOC_PROTECT_READS``, /metrics needs the key (its collection size, version, queue depth and
per-route counts are reads like any other; Prometheus sends the header from its scrape config), and /ready
still answers its status code to anyone (an orchestrator's probe carries no key) but says what it knows
(configuration, size, version, why it is not ready) only to a caller with the key. /health says nothing."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from app.api.deps import check_key, read_access
from app.api.errors import ApiError, error_response, error_responses
from app.api.schemas import HealthOut, ReadyOut

router = APIRouter()


@router.get("/health", response_model=HealthOut, summary="The process is alive")
def health() -> HealthOut:
    return HealthOut(status="ok")


@router.get(
    "/ready",
    response_model=ReadyOut,
    responses=error_responses(503),
    summary="Model, pipeline and index are loaded and writes are safe (503 until then; details need the key "
    "with GEOLOC_PROTECT_READS)",
)
def ready(request: Request, x_api_key: Annotated[str | None, Header()] = None):
    state = request.app.state
    detailed = _may_read(request, x_api_key)
    if state.service is None:
        return error_response("not_ready", (state.not_ready or "loading") if detailed else "loading")
    refusal = state.service.write_refusal
    if refusal is not None:  # the database files changed under this process (app/storage/integrity.py)
        return error_response("storage_unavailable", refusal if detailed else "the storage refuses writes")
    if not detailed:
        return ReadyOut(status="ready")
    r = state.service.readiness()
    return ReadyOut(
        status="ready",
        config=r.config,
        index_size=r.index_size,
        version=r.version,
        generation=r.generation,
        worker="in-process" if state.worker is not None and (state.writer is None or state.writer.held) else "external",
        database=r.database,
        index_loaded=r.index_loaded,
        index=r.index,
        index_choice=r.index_choice,
        calibration=r.calibration,
        features_backfill=state.backfill,
    )


def _may_read(request: Request, key: str | None) -> bool:
    """Whether this caller may read the details: always, unless GEOLOC_PROTECT_READS and no valid key."""
    if not request.app.state.settings.protect_reads:
        return True
    try:
        check_key(request, key)
    except ApiError:
        return False
    return True


@router.get(
    "/metrics",
    response_class=Response,
    responses=error_responses(401),
    dependencies=[Depends(read_access)],
    summary="Prometheus metrics (with GEOLOC_PROTECT_READS, the key too)",
)
def metrics(request: Request) -> Response:
    state = request.app.state
    if state.service is not None:
        state.metrics.observe(state.service.gauges())
    return Response(generate_latest(state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
