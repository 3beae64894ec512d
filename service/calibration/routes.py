"""A camera's calibration: status, history, forced re-solve and reset."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, status
from sqlalchemy.orm import Session

from service.calibration import repository
from service.calibration.schemas import (
    SOLUTION_FIELDS,
    CalibrationHistory,
    CalibrationRequested,
    CalibrationStatus,
    CalibrationVersionOut,
    solution_fields,
)
from service.calibration.service import people_needed
from service.cameras.service import require_camera
from service.dispatch import UNAVAILABLE_ERRORS
from service.http.dependencies import (
    CameraIdPath,
    DispatcherDep,
    ReadSessionDep,
    SessionDep,
    SettingsDep,
    nudge_best_effort,
    queue_unavailable,
)
from service.http.links import camera_url
from service.settings import Settings
from service.store.models import CalibrationVersion, Camera
from service.webhooks.events import announce, status_changed_deliveries

router = APIRouter(prefix="/v1/cameras", tags=["calibration"])


def version_out(version: CalibrationVersion) -> CalibrationVersionOut:
    return CalibrationVersionOut(
        version=version.version,
        epoch=version.epoch,
        status=version.status,  # type: ignore[arg-type]
        reason=version.reason,
        is_current=version.is_current,
        forced=version.forced,
        **solution_fields(version),
        evidence_count=version.evidence_count,
        duration_s=version.duration_s,
        created_at=version.created_at,
    )


def calibration_status(session: Session, camera: Camera, settings: Settings) -> CalibrationStatus:
    current = repository.current_calibration(session, camera.id)
    latest = repository.calibration_history(session, camera.id, limit=1)
    last_failure = latest[0].reason if latest and latest[0].status == "failed" else None
    needed = people_needed(session, camera, settings)
    if current is not None:
        state = "calibrated"
    elif needed == 0:
        state = "calibrating"
    else:
        state = "uncalibrated"
    fields = {
        "camera_id": camera.id,
        "status": state,
        "reason": camera.epoch_reason if current is None else None,
        "epoch": camera.epoch,
        "moved_at": camera.moved_at if camera.epoch_reason == "camera_moved" else None,
        "people_needed": needed,
        "evidence_count": camera.usable_evidence_count,
        "last_failure": last_failure,
    }
    if current is None:
        empty = dict.fromkeys((*SOLUTION_FIELDS, "version", "solved_evidence_count", "updated_at"))
        return CalibrationStatus(**fields, **empty)
    return CalibrationStatus(
        **fields,
        version=current.version,
        **solution_fields(current),
        solved_evidence_count=current.evidence_count,
        updated_at=current.created_at,
    )


@router.get("/{camera_id}/calibration", response_model=CalibrationStatus)
def get_calibration(camera_id: CameraIdPath, session: ReadSessionDep, settings: SettingsDep) -> CalibrationStatus:
    """The current calibration, or how much more evidence the camera needs."""
    return calibration_status(session, require_camera(session, camera_id), settings)


@router.get("/{camera_id}/calibration/history", response_model=CalibrationHistory)
def get_calibration_history(
    camera_id: CameraIdPath,
    session: ReadSessionDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Versions per page.")] = 100,
    # Versions are 32-bit integers; an unbounded one overflowed SQLite's INTEGER (a 500) before this bound.
    before: Annotated[int | None, Query(ge=1, le=2**31, description="Last version of the previous page.")] = None,
) -> CalibrationHistory:
    """Every solve, newest first, failed ones included (with their reason)."""
    require_camera(session, camera_id)
    versions = repository.calibration_history(session, camera_id, limit=limit, before_version=before)
    next_before = versions[-1].version if len(versions) == limit else None
    return CalibrationHistory(items=[version_out(v) for v in versions], next_before=next_before)


@router.post("/{camera_id}/calibration", status_code=status.HTTP_202_ACCEPTED, response_model=CalibrationRequested)
def request_calibration(
    camera_id: CameraIdPath, session: ReadSessionDep, dispatcher: DispatcherDep
) -> CalibrationRequested:
    """Force a re-solve now: its result becomes current even if less well supported than the current one."""
    require_camera(session, camera_id)
    try:
        dispatcher.calibration_requested(camera_id, forced=True)
    except UNAVAILABLE_ERRORS as exc:
        raise queue_unavailable("retry the request later.", exc) from exc
    return CalibrationRequested(camera_id=camera_id, forced=True, url=f"{camera_url(camera_id)}/calibration")


@router.delete("/{camera_id}/calibration", response_model=CalibrationStatus)
def reset_calibration(
    camera_id: CameraIdPath,
    session: SessionDep,
    settings: SettingsDep,
    dispatcher: DispatcherDep,
    drop_evidence: Annotated[
        bool, Query(description="Also delete the stored people (they stay stored for audit otherwise).")
    ] = False,
) -> CalibrationStatus:
    """Make the camera uncalibrated in a new calibration epoch: history and (unless dropped) people stay stored,
    but only people posted from now on feed its solves."""
    camera = require_camera(session, camera_id)
    was_calibrated = repository.current_calibration(session, camera_id) is not None
    repository.reset_calibration(session, camera_id, drop_evidence=drop_evidence)
    deliveries = status_changed_deliveries(session, camera_id, None, "calibrated", "reset") if was_calibrated else []
    session.commit()
    result = calibration_status(session, camera, settings)
    session.commit()
    announce(dispatcher, deliveries)
    if result.status == "calibrating":
        nudge_best_effort("request a solve after reset", dispatcher.calibration_requested, camera_id, forced=False)
    return result
