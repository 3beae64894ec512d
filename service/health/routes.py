"""Liveness (the process answers) and readiness (it can do its job: database and queue reachable)."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError

from service.health.schemas import Health, Readiness
from service.http.dependencies import DispatcherDep
from service.http.problems import ProblemError

router = APIRouter(tags=["health"])
log = logging.getLogger(__name__)


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """The process is up; says nothing about its dependencies (that is /readyz), so it never flaps with them."""
    return Health(status="ok")


@router.get("/readyz", response_model=Readiness, responses={503: {"description": "A dependency is unreachable"}})
def readyz(request: Request, dispatcher: DispatcherDep) -> Readiness:
    """200 when the database answers and the queue accepts work; 503 problem naming what is down otherwise."""
    checks: dict[str, str] = {}
    try:
        with request.app.state.engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        checks["database"] = "ok"
    except SQLAlchemyError as exc:
        log.warning("readiness: database unreachable: %s", exc)
        checks["database"] = f"unreachable: {type(exc).__name__}"
    try:
        checks["queue"] = "ok" if dispatcher.ready() else "not ready"
    except Exception as exc:  # any failure of the queue client means "not ready", never a 500
        log.warning("readiness: queue unreachable: %s", exc)
        checks["queue"] = f"unreachable: {type(exc).__name__}"
    down = {name: state for name, state in checks.items() if state != "ok"}
    if down:
        detail = "Not ready: " + ", ".join(f"{name} {state}" for name, state in down.items())
        raise ProblemError(503, "not-ready", detail, checks=checks)
    return Readiness(status="ready", checks=checks)
