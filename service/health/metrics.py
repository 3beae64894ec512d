"""GET /metrics: the Prometheus exposition of every process's metrics and the shared state (see
service.observability.metrics). An ordinary router, so whatever guards the API's routes guards it too; it
also needs an admin key, because it names every camera (Prometheus sends one with `authorization`)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response
from prometheus_client.exposition import choose_encoder

from service.keys.dependencies import require_admin
from service.observability.multiprocess import multiprocess_dir, sweep_dead_processes

router = APIRouter(tags=["observability"], dependencies=[Depends(require_admin)])


@router.get(
    "/metrics",
    response_class=Response,
    responses={
        200: {
            "description": "Prometheus text format (OpenMetrics when the Accept header asks for it)",
            "content": {"text/plain": {"schema": {"type": "string"}}},
        }
    },
)
def metrics(request: Request) -> Response:
    """Request latencies, frames ingested, jobs, pose inference and webhook deliveries from every process, plus
    queue depths and per-camera calibration state read now."""
    path = multiprocess_dir()
    if path is not None:
        sweep_dead_processes(path)
    encoder, content_type = choose_encoder(request.headers.get("accept", ""))
    return Response(encoder(request.app.state.metrics_registry), media_type=content_type)
