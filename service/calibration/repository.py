"""Calibration versions in the store: every solve appended, at most one current per camera, resets.

Functions flush but never commit: the caller owns the transaction, so a route or a job can combine several operations
(store a result and its violation events, say) atomically. Version numbers are allocated under a lock on the camera row,
one at a time.
"""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import delete, func, select, true, update
from sqlalchemy.orm import Session

from service.cameras.repository import existing_camera
from service.domain import CalibrationValues
from service.store.models import CALIBRATION_STATUSES, CalibrationVersion, Observation, finite_or_none, utc_now


def add_calibration(
    session: Session,
    camera_id: str,
    values: CalibrationValues,
    *,
    make_current: bool,
    forced: bool = False,
    now: datetime | None = None,
) -> CalibrationVersion:
    """Append the camera's next calibration version; it replaces the current one only if make_current.

    Whether a solve is good enough to become current is the caller's rule (the calibration worker's). Every
    solve, failed ones included, moves the camera's evidence_at_last_solve, so a camera that cannot be
    calibrated yet waits for more evidence instead of re-solving on every frame. The camera row is locked
    (PostgreSQL; SQLite transactions are exclusive anyway) so version numbers are allocated one at a time.
    """
    if values.status not in CALIBRATION_STATUSES:
        raise ValueError(f"status must be one of {CALIBRATION_STATUSES}, got {values.status!r}")
    if make_current and values.status != "ok":
        raise ValueError("only a successful calibration can become current")
    camera = existing_camera(session, camera_id, for_update=True)
    last = session.execute(
        select(func.max(CalibrationVersion.version)).where(CalibrationVersion.camera_id == camera_id)
    ).scalar_one()
    if make_current:
        # Before the insert, so the partial unique index never sees two current rows.
        session.execute(
            update(CalibrationVersion)
            .where(CalibrationVersion.camera_id == camera_id, CalibrationVersion.is_current == true())
            .values(is_current=False)
            .execution_options(synchronize_session="fetch")
        )
    normal = values.normal or (None, None, None)
    covariance = None
    if values.covariance is not None:
        covariance = [[finite_or_none(v) for v in row] for row in values.covariance]
    record = CalibrationVersion(
        camera_id=camera_id,
        version=(last or 0) + 1,
        status=values.status,
        reason=values.reason,
        fx_px=finite_or_none(values.fx_px),
        fy_px=finite_or_none(values.fy_px),
        cx_px=finite_or_none(values.cx_px),
        cy_px=finite_or_none(values.cy_px),
        normal_x=finite_or_none(normal[0]),
        normal_y=finite_or_none(normal[1]),
        normal_z=finite_or_none(normal[2]),
        rho_m=finite_or_none(values.rho_m),
        fx_std_px=finite_or_none(values.fx_std_px),
        fy_std_px=finite_or_none(values.fy_std_px),
        normal_std_deg=finite_or_none(values.normal_std_deg),
        rho_std_m=finite_or_none(values.rho_std_m),
        covariance=covariance,
        noise_px=finite_or_none(values.noise_px),
        distortion_k=finite_or_none(values.distortion_k),
        camera_model=values.camera_model,
        quality=values.quality,
        quality_grade=values.quality_grade,
        person_height_m=values.person_height_m,
        people_used=values.people_used,
        inliers=values.inliers,
        evidence_count=values.evidence_count,
        is_current=make_current,
        forced=forced,
        duration_s=finite_or_none(values.duration_s),
        created_at=now or utc_now(),
    )
    session.add(record)
    camera.evidence_at_last_solve = values.evidence_count
    session.flush()
    return record


def current_calibration(session: Session, camera_id: str) -> CalibrationVersion | None:
    stmt = select(CalibrationVersion).where(
        CalibrationVersion.camera_id == camera_id, CalibrationVersion.is_current == true()
    )
    return session.execute(stmt).scalar_one_or_none()


def get_calibration(session: Session, camera_id: str, version: int) -> CalibrationVersion | None:
    stmt = select(CalibrationVersion).where(
        CalibrationVersion.camera_id == camera_id, CalibrationVersion.version == version
    )
    return session.execute(stmt).scalar_one_or_none()


def calibration_history(
    session: Session, camera_id: str, *, limit: int = 100, before_version: int | None = None
) -> list[CalibrationVersion]:
    """Versions newest first, a page at a time (pass the last version of a page as before_version)."""
    stmt = select(CalibrationVersion).where(CalibrationVersion.camera_id == camera_id)
    if before_version is not None:
        stmt = stmt.where(CalibrationVersion.version < before_version)
    return list(session.scalars(stmt.order_by(CalibrationVersion.version.desc()).limit(limit)))


def reset_calibration(session: Session, camera_id: str, *, drop_evidence: bool = False) -> None:
    """Make the camera uncalibrated again (history is kept); optionally forget its stored observations too.

    Dropping evidence is what a moved camera or a changed resolution needs: old people no longer fit the view.
    """
    camera = existing_camera(session, camera_id, for_update=True)
    session.execute(
        update(CalibrationVersion)
        .where(CalibrationVersion.camera_id == camera_id, CalibrationVersion.is_current == true())
        .values(is_current=False)
        .execution_options(synchronize_session="fetch")
    )
    camera.evidence_at_last_solve = 0
    if drop_evidence:
        session.execute(delete(Observation).where(Observation.camera_id == camera_id))
        camera.usable_evidence_count = 0
    session.flush()
