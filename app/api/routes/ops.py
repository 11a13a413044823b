"""Operations: /health (alive), /ready (loaded, 503 until then), /metrics (Prometheus)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from app.api.errors import error_response, error_responses
from app.api.schemas import HealthOut, ReadyOut

router = APIRouter()


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
    if state.service is None:
        return error_response("not_ready", state.load_error or "loading")
    col = state.service.collection
    col.catch_up()
    return ReadyOut(
        status="ready",
        config=col.pipeline.config.name,
        index_size=col.size,
        version=col.version,
        generation=col.generation,
        worker="in-process" if state.worker is not None and (state.writer is None or state.writer.held) else "external",
        database=state.service.store.engine,
        index_loaded="rebuilt" if col.stats.full_rebuilds else "snapshot",
        calibration=col.calibration_summary(),
    )


@router.get("/metrics", response_class=Response, summary="Prometheus metrics")
def metrics(request: Request) -> Response:
    state = request.app.state
    if state.service is not None:
        state.metrics.observe_collection(state.service.collection)
    return Response(generate_latest(state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
