"""Read-only summaries of the whole store for monitoring: one query each, whatever the amount of data stored."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import and_, select, true
from sqlalchemy.orm import Session

from service.store.models import CalibrationVersion, Camera


@dataclass(frozen=True)
class CameraOverview:
    """A camera's calibration state as the metrics report it."""

    camera_id: str
    usable_evidence: int
    calibration_version: int | None
    """The current calibration's version; None while the camera is uncalibrated."""
    calibrated_at: datetime | None
    epoch: int = 1
    moves: int = 0
    """Moves the movement test has found over the camera's life."""


def camera_overview(session: Session) -> list[CameraOverview]:
    """Every camera with its current calibration, in one query: the partial unique index on current versions
    makes the outer join one index probe per camera, and the evidence count is a column kept on insert."""
    stmt = (
        select(
            Camera.id,
            Camera.usable_evidence_count,
            CalibrationVersion.version,
            CalibrationVersion.created_at,
            Camera.epoch,
            Camera.moves,
        )
        .outerjoin(
            CalibrationVersion,
            and_(CalibrationVersion.camera_id == Camera.id, CalibrationVersion.is_current == true()),
        )
        .order_by(Camera.id)
    )
    return [
        CameraOverview(camera_id, int(evidence), version, created_at, int(epoch), int(moves))
        for camera_id, evidence, version, created_at, epoch, moves in session.execute(stmt)
    ]
