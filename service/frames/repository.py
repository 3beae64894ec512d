"""Frames in the store, once stored: their images and people, pending work, measured results; frames failed wholesale.

How frames and their people get in is service.frames.ingest. Functions flush but never commit: the caller owns the
transaction, so a job can combine several operations (store a result and its violation events, say) atomically.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from datetime import datetime
from typing import Any, cast

from sqlalchemy import Row, Table, Text, bindparam, delete, func, insert, select, true, update
from sqlalchemy import cast as sa_cast
from sqlalchemy.orm import Session, defer

from service.domain import FrameOutcome
from service.store.models import (
    FRAME_ERROR_MAX_LENGTH,
    CalibrationVersion,
    Camera,
    Frame,
    FrameImage,
    Observation,
    ViolationEvent,
    clip_reason,
    utc_now,
)
from service.violations.repository import violation_rows

_OBSERVATIONS = cast(Table, Observation.__table__)
_FRAMES = cast(Table, Frame.__table__)
_VIOLATION_EVENTS = cast(Table, ViolationEvent.__table__)


def frame_image(session: Session, frame_id: uuid.UUID) -> FrameImage | None:
    return session.get(FrameImage, frame_id)


def frame_image_kept(session: Session, frame_id: uuid.UUID) -> bool:
    """Whether the frame's image is stored, without loading its bytes."""
    return session.scalar(select(func.count()).where(FrameImage.frame_id == frame_id)) == 1


def frames_detecting(session: Session) -> list[tuple[str, uuid.UUID]]:
    """(camera_id, frame_id) of image frames waiting for their pose job, oldest first (worker start-up)."""
    stmt = select(Frame.camera_id, Frame.id).where(Frame.status == "detecting").order_by(Frame.received_at, Frame.id)
    return [(camera_id, frame_id) for camera_id, frame_id in session.execute(stmt)]


def delete_kept_images(session: Session, camera_id: str) -> int:
    """Forget a camera's kept images (it stopped keeping them); images still awaiting pose stay until used."""
    done = select(Frame.id).where(Frame.camera_id == camera_id, Frame.status != "detecting")
    result = session.execute(delete(FrameImage).where(FrameImage.frame_id.in_(done)))
    return int(result.rowcount)  # type: ignore[attr-defined]


def fail_unfinished_frames(session: Session, camera_id: str, reason: str) -> int:
    """Fail the camera's frames still waiting for pose or measuring, with `reason`; returns how many.

    For a resize: such frames were checked against the old image size, so an image's people must not join the new
    size's evidence and a frame's people (dropped with the evidence) must not be measured with its calibration.
    Their images go too, unless the camera keeps images.
    """
    waiting = (_FRAMES.c.camera_id == camera_id) & _FRAMES.c.status.in_(("detecting", "pending"))
    keeps_images = session.scalar(select(Camera.keep_images).where(Camera.id == camera_id))
    if not keeps_images:
        session.execute(delete(FrameImage).where(FrameImage.frame_id.in_(select(_FRAMES.c.id).where(waiting))))
    failed = session.execute(
        update(_FRAMES)
        .where(waiting)
        .values(status="failed", error=clip_reason(reason, FRAME_ERROR_MAX_LENGTH), processed_at=utc_now())
        .execution_options(synchronize_session=False)
    )
    return int(failed.rowcount)  # type: ignore[attr-defined]


def get_frame(session: Session, camera_id: str, frame_id: uuid.UUID) -> Frame | None:
    """A frame, only if it belongs to that camera (a frame id alone must not reveal another camera's data)."""
    frame = session.get(Frame, frame_id)
    return frame if frame is not None and frame.camera_id == camera_id else None


def get_frame_with_encoded_result(
    session: Session, camera_id: str, frame_id: uuid.UUID
) -> tuple[Frame, str | None] | None:
    """A frame (as get_frame) and its result as the stored JSON text, which `frame.result` then does not hold.

    For callers that send the result on as it is: decoding 190 pairs only to encode them again was most of the
    cost of answering a poll for a measured frame."""
    stmt = (
        select(Frame, sa_cast(Frame.result, Text))
        .where(Frame.id == frame_id, Frame.camera_id == camera_id)
        .options(defer(Frame.result, raiseload=True))
    )
    row = session.execute(stmt).one_or_none()
    return None if row is None else (row[0], row[1])


def frame_observations(session: Session, frame_id: uuid.UUID) -> list[Observation]:
    """A frame's people in posted order: what a distance computation measures."""
    return frames_observations(session, [frame_id]).get(frame_id, [])


def frames_observations(session: Session, frame_ids: Sequence[uuid.UUID]) -> dict[uuid.UUID, list[Observation]]:
    """Several frames' people in one query (a worker measuring a batch), each frame's in posted order."""
    people: dict[uuid.UUID, list[Observation]] = {}
    if not frame_ids:
        return people
    stmt = (
        select(Observation)
        .where(Observation.frame_id.in_(frame_ids))
        .order_by(Observation.frame_id, Observation.person_index)
    )
    for observation in session.scalars(stmt):
        people.setdefault(observation.frame_id, []).append(observation)
    return people


def frames_points(session: Session, frame_ids: Sequence[uuid.UUID]) -> dict[uuid.UUID, list[Row[Any]]]:
    """Several frames' people as light rows of their centres (`shoulder_x_px` ... `ankle_y_px`), whether they
    are usable evidence (`usable`) and why not (`unusable_reason`), what measuring reads of the verdict
    (`posture`, `placed_from_box`, `static`) and the client's track id (`client_track_id`, echoed in the result),
    posted order.

    What measuring needs, and all it needs: building full ORM objects for a worker's batch (a thousand people)
    cost more than measuring them.
    """
    people: dict[uuid.UUID, list[Row[Any]]] = {}
    if not frame_ids:
        return people
    columns = _OBSERVATIONS.c
    stmt = (
        select(
            columns.frame_id,
            columns.shoulder_x_px,
            columns.shoulder_y_px,
            columns.ankle_x_px,
            columns.ankle_y_px,
            columns.usable,
            columns.unusable_reason,
            columns.client_track_id,
            columns.posture,
            columns.placed_from_box,
            columns.static,
        )
        .where(columns.frame_id.in_(frame_ids))
        .order_by(columns.frame_id, columns.person_index)
    )
    for row in session.execute(stmt):
        people.setdefault(row.frame_id, []).append(row)
    return people


def seen_people_boxes(session: Session, camera_id: str, epoch: int, frames: int) -> list[tuple[float, ...]]:
    """The detector boxes of the usable people (whole, standing) in the camera's latest `frames` image frames
    whose people are stored (measured or waiting for a calibration), of its current epoch: how tall people appear
    where, for the next frame's search.

    The frames come newest first off the camera's (camera_id, timestamp, id) index."""
    latest = (
        select(_FRAMES.c.id)
        .where(
            _FRAMES.c.camera_id == camera_id,
            _FRAMES.c.source == "image",
            _FRAMES.c.status.in_(("pending", "done")),
        )
        .order_by(_FRAMES.c.timestamp.desc(), _FRAMES.c.id.desc())
        .limit(frames)
        .scalar_subquery()
    )
    columns = _OBSERVATIONS.c
    stmt = select(columns.box_left_px, columns.box_top_px, columns.box_right_px, columns.box_bottom_px).where(
        columns.frame_id.in_(latest),
        columns.epoch == epoch,
        columns.usable.is_(True),
        columns.box_left_px.is_not(None),
    )
    return [tuple(row) for row in session.execute(stmt)]


def pending_frames(session: Session, camera_id: str | None = None, *, limit: int | None = None) -> list[Frame]:
    """Frames still waiting for a result, oldest first; all cameras when camera_id is None (worker start-up)."""
    stmt = select(Frame).where(Frame.status == "pending")
    if camera_id is not None:
        stmt = stmt.where(Frame.camera_id == camera_id)
    stmt = stmt.order_by(Frame.received_at, Frame.id)
    if limit is not None:
        stmt = stmt.limit(limit)
    return list(session.scalars(stmt))


def cameras_with_pending_frames(session: Session, *, calibrated_only: bool = False) -> list[str]:
    """Cameras that have frames waiting to be measured (the workers' recovery pass); with `calibrated_only`, only
    those with a current calibration (the others' frames are measured when their first solve becomes current)."""
    stmt = select(Frame.camera_id).where(Frame.status == "pending")
    if calibrated_only:
        current = select(CalibrationVersion.id).where(
            CalibrationVersion.camera_id == Frame.camera_id, CalibrationVersion.is_current == true()
        )
        stmt = stmt.where(current.exists())
    return list(session.scalars(stmt.distinct().order_by(Frame.camera_id)))


def record_frame_outcomes(session: Session, outcomes: Sequence[FrameOutcome], *, now: datetime | None = None) -> int:
    """Store many frames' results and replace their violation events, in a few statements (a worker's batch).

    Returns how many frames were updated; a frame deleted meanwhile (its camera was) is simply not among them.
    """
    if not outcomes:
        return 0
    now = now or utc_now()
    events = []
    for outcome in outcomes:
        if outcome.status not in ("done", "failed"):
            raise ValueError(f"an outcome is done or failed, got {outcome.status!r}")
        events += violation_rows(outcome.camera_id, outcome.frame_id, outcome.timestamp, outcome.violations)
    updated = session.execute(
        update(_FRAMES).where(_FRAMES.c.id == bindparam("frame_id")),
        [
            {
                "frame_id": o.frame_id,
                "status": o.status,
                "result": o.result,
                "calibration_version": o.calibration_version,
                "error": o.error,
                "processed_at": now,
            }
            for o in outcomes
        ],
    )
    frame_ids = [o.frame_id for o in outcomes]
    session.execute(delete(ViolationEvent).where(ViolationEvent.frame_id.in_(frame_ids)))
    if events:
        live = set(session.scalars(select(Frame.id).where(Frame.id.in_(frame_ids))))
        events = [row for row in events if row["frame_id"] in live]
    if events:
        session.execute(insert(_VIOLATION_EVENTS), events)
    session.expire_all()
    return int(updated.rowcount)  # type: ignore[attr-defined]
