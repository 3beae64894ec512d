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
from service.store.models import (
    CALIBRATION_STATUSES,
    CalibrationVersion,
    Camera,
    Frame,
    MovementMonitor,
    Observation,
    ViolationEvent,
    finite_or_none,
    utc_now,
)


def add_calibration(
    session: Session,
    camera_id: str,
    values: CalibrationValues,
    *,
    make_current: bool,
    forced: bool = False,
    now: datetime | None = None,
    epoch: int | None = None,
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
    epoch = camera.epoch if epoch is None else epoch
    stale = epoch != camera.epoch
    make_current = make_current and not stale
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
        epoch=epoch,
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
    if not stale:
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


def _close_epoch(session: Session, camera: Camera, reason: str, moved_at: datetime | None) -> None:
    """Open the camera's next epoch: no version is current, the movement test starts again and the evidence
    counters start from nothing (the caller counts what the new epoch already holds)."""
    session.execute(
        update(CalibrationVersion)
        .where(CalibrationVersion.camera_id == camera.id, CalibrationVersion.is_current == true())
        .values(is_current=False)
        .execution_options(synchronize_session="fetch")
    )
    session.execute(delete(MovementMonitor).where(MovementMonitor.camera_id == camera.id))
    camera.epoch += 1
    camera.epoch_reason = reason
    camera.moved_at = moved_at
    camera.evidence_at_last_solve = 0
    camera.usable_evidence_count = 0
    camera.updated_at = utc_now()


def reset_calibration(session: Session, camera_id: str, *, drop_evidence: bool = False, reason: str = "reset") -> None:
    """Make the camera uncalibrated again in a new epoch: history and (unless dropped) its people stay stored,
    but nothing from before feeds a solve any more.

    Dropping evidence is what a changed resolution needs (old people's pixels mean nothing in the new image); a
    user who resets a camera that moved can keep them for audit.
    """
    camera = existing_camera(session, camera_id, for_update=True)
    _close_epoch(session, camera, reason, None)
    if drop_evidence:
        session.execute(delete(Observation).where(Observation.camera_id == camera_id))
    session.flush()


def withdraw_current(session: Session, camera_id: str) -> None:
    """No version of the camera is current any more, in the same epoch with the same people: what a changed camera
    model needs (its principal point, focal length or lens), since the current solution belongs to another camera
    model while the people's pixels are as good as before. The next solve is due at once, and the movement test
    starts again with it (its state is relative to the version it watched)."""
    camera = existing_camera(session, camera_id, for_update=True)
    session.execute(
        update(CalibrationVersion)
        .where(CalibrationVersion.camera_id == camera_id, CalibrationVersion.is_current == true())
        .values(is_current=False)
        .execution_options(synchronize_session="fetch")
    )
    session.execute(delete(MovementMonitor).where(MovementMonitor.camera_id == camera_id))
    camera.evidence_at_last_solve = 0
    camera.updated_at = utc_now()
    session.flush()


def open_epoch_after_move(session: Session, camera_id: str, *, from_epoch: int, moved_at: datetime) -> bool:
    """The camera moved at `moved_at` (the first frame of the new view): open its next epoch, unless `from_epoch`
    is already closed (a reset or another move won the race); returns whether it opened one.

    Frames from `moved_at` on belong to the new view: their people join the new epoch (the evidence it starts
    with), and those already measured with the old calibration lose their results and violation events and wait
    to be measured again once the new epoch calibrates.
    """
    camera = existing_camera(session, camera_id, for_update=True)
    if camera.epoch != from_epoch:
        return False
    _close_epoch(session, camera, "camera_moved", moved_at)
    camera.moves += 1
    new_view = select(Frame.id).where(Frame.camera_id == camera_id, Frame.timestamp >= moved_at)
    session.execute(
        update(Observation)
        .where(Observation.camera_id == camera_id, Observation.epoch == from_epoch, Observation.frame_id.in_(new_view))
        .values(epoch=camera.epoch)
        .execution_options(synchronize_session=False)
    )
    session.execute(
        delete(ViolationEvent)
        .where(ViolationEvent.camera_id == camera_id, ViolationEvent.frame_id.in_(new_view))
        .execution_options(synchronize_session=False)
    )
    session.execute(
        update(Frame)
        .where(Frame.camera_id == camera_id, Frame.timestamp >= moved_at, Frame.calibration_version.is_not(None))
        .values(status="pending", result=None, calibration_version=None, error=None, processed_at=None)
        .execution_options(synchronize_session=False)
    )
    camera.usable_evidence_count = session.execute(
        select(func.count()).where(
            Observation.camera_id == camera_id, Observation.epoch == camera.epoch, Observation.usable == true()
        )
    ).scalar_one()
    session.flush()
    return True


def movement_state(session: Session, camera_id: str) -> MovementMonitor | None:
    return session.get(MovementMonitor, camera_id)


def save_movement_state(
    session: Session, camera_id: str, *, epoch: int, calibration_version: int, state: bytes, statistic: float
) -> None:
    """Keep the movement test's state for the camera's next measuring job (one row per camera)."""
    row = session.get(MovementMonitor, camera_id)
    if row is None:
        row = MovementMonitor(camera_id=camera_id)
        session.add(row)
    row.epoch, row.calibration_version, row.state, row.statistic = epoch, calibration_version, state, statistic
    row.updated_at = utc_now()
    session.flush()
