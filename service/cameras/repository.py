"""Cameras in the store: idempotent create/update, read, list, delete.

Functions flush but never commit: the caller owns the transaction, so a route or a job can combine several operations
(store a result and its violation events, say) atomically. A camera upsert that races with another process runs its
insert inside a SAVEPOINT and resolves the unique-constraint collision by reading the winner's row, so a retry never
fails.
"""

from __future__ import annotations

from collections.abc import Collection
from datetime import datetime
from typing import Any

from sqlalchemy import bindparam, delete, select
from sqlalchemy.engine import Connection
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.domain import CameraCounters
from service.store.models import DEFAULT_DISTANCE_THRESHOLD_M, Camera, utc_now

# The camera model the installer may know (issue 16), each nullable.
CAMERA_MODEL_COLUMNS = (
    "known_focal_y_px",
    "principal_point_x_px",
    "principal_point_y_px",
    "distortion_coefficients",
    "camera_height_m",
    "camera_height_tolerance_m",
)


class CameraNotFoundError(LookupError):
    """The camera id is not configured (the API answers 404)."""


class CameraResizedError(Exception):
    """The camera's image size is no longer the one its frame was checked against (a PUT changed it since): the
    frame is not stored, so no person checked against the old size joins the new size's evidence."""

    def __init__(self, camera_id: str, size_px: tuple[int, int]) -> None:
        super().__init__(f"camera {camera_id!r} is now {size_px[0]}x{size_px[1]} px")
        self.camera_id = camera_id
        self.size_px = size_px


_COUNTERS = select(Camera.id, Camera.epoch, Camera.usable_evidence_count, Camera.evidence_at_last_solve).where(
    Camera.id.in_(bindparam("ids", expanding=True))
)


def camera_counters(connection: Connection, camera_ids: Collection[str]) -> dict[str, CameraCounters]:
    """The evidence counters of these cameras (the ones that exist), in one Core statement on the connection: the
    write batch reads them in its transaction, the after-commit due-solve check for cameras it was not handed."""
    rows = connection.execute(_COUNTERS, {"ids": sorted(camera_ids)})
    return {row.id: CameraCounters(row.epoch, row.usable_evidence_count, row.evidence_at_last_solve) for row in rows}


def existing_camera(session: Session, camera_id: str, *, for_update: bool = False) -> Camera:
    """The camera's row, read afresh (locked with `for_update`); CameraNotFoundError when there is none."""
    stmt = select(Camera).where(Camera.id == camera_id).execution_options(populate_existing=True)
    if for_update:
        stmt = stmt.with_for_update()
    camera = session.execute(stmt).scalar_one_or_none()
    if camera is None:
        raise CameraNotFoundError(camera_id)
    return camera


def upsert_camera(
    session: Session,
    camera_id: str,
    *,
    image_width_px: int,
    image_height_px: int,
    person_height_m: float,
    equal_focal: bool = True,
    distance_threshold_m: float = DEFAULT_DISTANCE_THRESHOLD_M,
    known_focal_px: float | None = None,
    keep_images: bool = False,
    camera_model: dict[str, Any] | None = None,
    now: datetime | None = None,
) -> tuple[Camera, bool]:
    """Create or update a camera's settings; returns (camera, created) so PUT can answer 201 or 200.

    person_height_m has no default here: the API owns the default (service.geometry.DEFAULT_HEIGHT_M).

    `camera_model` holds the optional intrinsics columns by name (known_focal_y_px, principal_point_x_px, ...);
    a column it does not name is cleared, since a PUT replaces the whole settings.

    Changing the image size does not touch stored evidence: deciding whether old observations still apply
    (and resetting them with reset_calibration) is the API's policy.
    """
    now = now or utc_now()
    values: dict[str, Any] = {
        "image_width_px": image_width_px,
        "image_height_px": image_height_px,
        "person_height_m": person_height_m,
        "equal_focal": equal_focal,
        "distance_threshold_m": distance_threshold_m,
        "known_focal_px": known_focal_px,
        "keep_images": keep_images,
        **dict.fromkeys(CAMERA_MODEL_COLUMNS),
        **(camera_model or {}),
    }
    unknown = set(values) - set(Camera.__table__.columns.keys())
    if unknown:
        raise ValueError(f"not camera columns: {sorted(unknown)}")
    camera = session.get(Camera, camera_id)
    if camera is None:
        try:
            with session.begin_nested():
                camera = Camera(id=camera_id, created_at=now, updated_at=now, **values)
                session.add(camera)
            return camera, True
        except IntegrityError:
            # Either a concurrent PUT created it first (update it below) or the values break a constraint.
            camera = session.get(Camera, camera_id)
            if camera is None:
                raise
    changed = False
    for name, value in values.items():
        if getattr(camera, name) != value:
            setattr(camera, name, value)
            changed = True
    if changed:
        camera.updated_at = now
        session.flush()
    return camera, False


def get_camera(session: Session, camera_id: str) -> Camera | None:
    return session.get(Camera, camera_id)


def list_cameras(
    session: Session, *, limit: int = 100, after: str | None = None, only: Collection[str] | None = None
) -> list[Camera]:
    """Cameras in id order, a page at a time: pass the last id of a page as `after` for the next one.

    `only` restricts the listing to those ids (a camera-scoped API key); None lists every camera.
    """
    stmt = select(Camera).order_by(Camera.id).limit(limit)
    if after is not None:
        stmt = stmt.where(Camera.id > after)
    if only is not None:
        stmt = stmt.where(Camera.id.in_(sorted(only)))
    return list(session.scalars(stmt))


def delete_camera(session: Session, camera_id: str) -> bool:
    """Delete a camera and, by ON DELETE CASCADE, all its frames, observations, calibrations and events."""
    result = session.execute(delete(Camera).where(Camera.id == camera_id))
    return bool(result.rowcount)  # type: ignore[attr-defined]
