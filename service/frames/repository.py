"""Frames in the store: keypoint and image frames with their people, pose results, pending work, measured results.

Functions flush but never commit: the caller owns the transaction, so a route or a job can combine several operations
(store a result and its violation events, say) atomically. An idempotent frame insert that races with a retry of itself
runs inside a SAVEPOINT and resolves the unique-constraint collision by reading the winner's frame, so a retry never
fails and never stores its people twice.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from datetime import datetime
from typing import Any, cast

import numpy as np
import uuid6
from sqlalchemy import Row, Table, Text, and_, bindparam, delete, func, insert, or_, select, true, update
from sqlalchemy import cast as sa_cast
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, defer, make_transient_to_detached

from service.cameras.repository import CameraNotFoundError, existing_camera
from service.domain import FrameOutcome, PersonIn, Point
from service.geometry.evidence import grid_cells
from service.store.models import (
    FRAME_ERROR_MAX_LENGTH,
    CalibrationVersion,
    Camera,
    Frame,
    FrameImage,
    Observation,
    ViolationEvent,
    clip_reason,
    pack_keypoints,
    utc_now,
)
from service.violations.repository import violation_rows

# Bulk inserts go through the Core tables: ~15% less overhead per frame than ORM bulk inserts.
_OBSERVATIONS = cast(Table, Observation.__table__)
_FRAMES = cast(Table, Frame.__table__)
_CAMERAS = cast(Table, Camera.__table__)
_VIOLATION_EVENTS = cast(Table, ViolationEvent.__table__)
_FRAME_COLUMNS = (
    "id",
    "camera_id",
    "client_frame_id",
    "timestamp",
    "received_at",
    "source",
    "status",
    "people",
    "pose_model",
    "request_id",
)


@dataclass(frozen=True)
class NewKeypointFrame:
    """A posted keypoint frame on its way into the store (see add_keypoint_frames)."""

    camera: Camera
    """The frame's camera as the caller read it; only its id and image size are used."""
    timestamp: datetime
    people: Sequence[PersonIn]
    client_frame_id: str | None = None
    request_id: str | None = None
    """The posting request's id, kept so the jobs that handle the frame log under it."""


def _check_point(name: str, point: Point | None) -> None:
    if point is not None and not (len(point) == 2 and all(math.isfinite(float(v)) for v in point)):
        raise ValueError(f"{name} must be two finite pixel coordinates, got {point!r}")


def _observation_rows(camera: Camera, frame_id: uuid.UUID, people: Sequence[PersonIn]) -> list[dict[str, Any]]:
    for person in people:
        _check_point("shoulder_px", person.shoulder_px)
        _check_point("ankle_px", person.ankle_px)
    size_px = (camera.image_width_px, camera.image_height_px)
    ankles = [person.ankle_px for person in people if person.ankle_px is not None]
    cells = iter(grid_cells(np.array(ankles, dtype=float), size_px).tolist() if ankles else ())
    rows = []
    for index, person in enumerate(people):
        reason = person.unusable_reason
        if reason is None and person.shoulder_px is None:
            reason = "shoulder centre not visible"
        if reason is None and person.ankle_px is None:
            reason = "ankle centre not visible"
        shoulder = person.shoulder_px or (None, None)
        ankle = person.ankle_px or (None, None)
        box = person.box_px or (None, None, None, None)
        cell = None if person.ankle_px is None else next(cells)
        rows.append(
            {
                "camera_id": camera.id,
                "frame_id": frame_id,
                "person_index": index,
                "shoulder_x_px": shoulder[0],
                "shoulder_y_px": shoulder[1],
                "ankle_x_px": ankle[0],
                "ankle_y_px": ankle[1],
                "keypoints_f32": None if person.keypoints is None else pack_keypoints(person.keypoints),
                "box_left_px": box[0],
                "box_top_px": box[1],
                "box_right_px": box[2],
                "box_bottom_px": box[3],
                "detection_score": person.detection_score,
                "usable": reason is None,
                "unusable_reason": reason,
                "cell": cell,
                "sample_key": None,  # keyed in bulk by the calibration job: key_new_evidence
            }
        )
    return rows


def _frame_row(frame: Frame) -> dict[str, Any]:
    return {column: getattr(frame, column) for column in _FRAME_COLUMNS}


def _insert_observations(session: Session, camera_id: str, rows: Sequence[dict[str, Any]]) -> None:
    """Insert a frame's people and count its usable ones on the camera (the counter that drives re-solves)."""
    if not rows:
        return
    session.execute(insert(_OBSERVATIONS), rows)
    _count_evidence(session, {camera_id: sum(1 for row in rows if row["usable"])})


_COUNT_EVIDENCE = (
    update(_CAMERAS)
    .where(_CAMERAS.c.id == bindparam("camera"))
    .values(usable_evidence_count=_CAMERAS.c.usable_evidence_count + bindparam("usable"))
)


def _count_evidence(session: Session, usable: dict[str, int]) -> None:
    """Add newly stored usable people to their cameras' counters: one Core statement, executed once per camera by
    the driver (executemany), inside the writer's transaction, which holds SQLite's one write lock."""
    rows = [{"camera": camera_id, "usable": n} for camera_id, n in usable.items() if n]
    if rows:
        session.execute(_COUNT_EVIDENCE, rows)


def _frame_by_client_id(session: Session, camera_id: str, client_frame_id: str) -> Frame | None:
    stmt = select(Frame).where(Frame.camera_id == camera_id, Frame.client_frame_id == client_frame_id)
    return session.execute(stmt).scalar_one_or_none()


def add_keypoint_frame(
    session: Session,
    camera_id: str,
    *,
    timestamp: datetime,
    people: Sequence[PersonIn],
    client_frame_id: str | None = None,
    received_at: datetime | None = None,
    camera: Camera | None = None,
    request_id: str | None = None,
) -> tuple[Frame, bool]:
    """Store a frame and its people atomically; returns (frame, created).

    A frame posted again with the same client frame id (a client retry, possibly racing the original) returns
    the stored frame with created=False and stores nothing, so evidence is never counted twice. `camera`, when
    the caller has already read it (the API, in a read-only session), saves reading it again inside the write
    transaction; only its image size is used, and a camera deleted meanwhile is still refused (foreign key).
    `request_id` is the posting request's id, kept so the jobs that handle the frame log under it.
    """
    _check_timestamp(timestamp)
    if camera is None:
        camera = existing_camera(session, camera_id)
    if client_frame_id is not None:
        existing = _frame_by_client_id(session, camera_id, client_frame_id)
        if existing is not None:
            return existing, False
    # The rows go in as Core inserts, which cost a fraction of an ORM flush.
    frame = _new_frame(
        camera_id, timestamp, client_frame_id, received_at or utc_now(), people=len(people), request_id=request_id
    )
    rows = _observation_rows(camera, frame.id, people)
    try:
        # A savepoint only where a unique-id race is possible: it costs two statements on the hot path.
        with session.begin_nested() if client_frame_id is not None else nullcontext():
            session.execute(insert(_FRAMES), [_frame_row(frame)])
            _insert_observations(session, camera_id, rows)
    except IntegrityError:
        existing = None
        if client_frame_id is not None:
            existing = _frame_by_client_id(session, camera_id, client_frame_id)
        if existing is not None:
            return existing, False
        if session.get(Camera, camera_id) is None:
            raise CameraNotFoundError(camera_id) from None
        raise
    if camera in session:
        session.expire(camera, ["usable_evidence_count"])
    _attach_inserted(session, frame)
    return frame, True


def add_keypoint_frames(
    session: Session, frames: Sequence[NewKeypointFrame], *, received_at: datetime | None = None
) -> list[tuple[Frame, bool]]:
    """Store several frames and their people with one statement per table; returns (frame, created) per frame.

    The API's group commit (service.frames.writer) writes the frames that arrive while the previous batch
    is being written in one transaction, which costs a fraction of one transaction per frame. Retries are
    answered as in add_keypoint_frame: a client frame id already stored, or repeated within the batch, returns
    the first frame with created=False. Unlike add_keypoint_frame there is no SAVEPOINT per frame: a frame whose
    camera was deleted meanwhile, or whose client id another process stored since the check, makes the whole
    batch raise IntegrityError, and the caller stores those frames one at a time instead.
    """
    received_at = received_at or utc_now()
    for item in frames:
        _check_timestamp(item.timestamp)
    known = _frames_by_client_ids(session, frames)
    results: list[tuple[Frame, bool]] = []
    frame_rows: list[dict[str, Any]] = []
    observation_rows: list[dict[str, Any]] = []
    usable: dict[str, int] = {}
    for item in frames:
        camera_id = item.camera.id
        key = (camera_id, item.client_frame_id)
        if item.client_frame_id is not None and key in known:
            results.append((known[key], False))
            continue
        frame = _new_frame(
            camera_id,
            item.timestamp,
            item.client_frame_id,
            received_at,
            people=len(item.people),
            request_id=item.request_id,
        )
        if item.client_frame_id is not None:
            known[key] = frame
        rows = _observation_rows(item.camera, frame.id, item.people)
        frame_rows.append(_frame_row(frame))
        observation_rows += rows
        usable[camera_id] = usable.get(camera_id, 0) + sum(1 for row in rows if row["usable"])
        results.append((frame, True))
    if frame_rows:
        session.execute(insert(_FRAMES), frame_rows)
    if observation_rows:
        session.execute(insert(_OBSERVATIONS), observation_rows)
    _count_evidence(session, usable)
    for frame, created in results:
        if created:
            _attach_inserted(session, frame)
    return results


def _frames_by_client_ids(session: Session, frames: Sequence[NewKeypointFrame]) -> dict[tuple[str, str | None], Frame]:
    """Stored frames among the batch's client frame ids, by (camera id, client frame id): one query for the whole
    batch, an OR of one index lookup per camera (SQLite scans the table for the row-value IN that would say it
    more briefly)."""
    wanted: dict[str, set[str]] = {}
    for item in frames:
        if item.client_frame_id is not None:
            wanted.setdefault(item.camera.id, set()).add(item.client_frame_id)
    if not wanted:
        return {}
    stmt = select(Frame).where(
        or_(
            *(
                and_(Frame.camera_id == camera_id, Frame.client_frame_id.in_(sorted(client_ids)))
                for camera_id, client_ids in sorted(wanted.items())
            )
        )
    )
    return {(frame.camera_id, frame.client_frame_id): frame for frame in session.execute(stmt).scalars()}


def _check_timestamp(timestamp: datetime) -> None:
    if timestamp.tzinfo is None or timestamp.utcoffset() is None:
        raise ValueError(f"timestamp {timestamp!r} has no timezone: the store keeps UTC instants")


def _new_frame(
    camera_id: str,
    timestamp: datetime,
    client_frame_id: str | None,
    received_at: datetime,
    *,
    source: str = "keypoints",
    people: int = 0,
    request_id: str | None = None,
) -> Frame:
    """A frame not yet inserted: keypoint frames wait to be measured, image frames for their pose job first.

    Its id is a UUIDv7, time-ordered: a random v4 id put every frame on its own page of the frames table's and the
    observations' (frame_id, person_index) indexes, a sixth of the bytes written per stored frame.
    """
    return Frame(
        id=uuid.UUID(int=uuid6.uuid7().int),  # a plain UUID: uuid6's subclass must not leak into pickles
        camera_id=camera_id,
        client_frame_id=client_frame_id,
        timestamp=timestamp,
        received_at=received_at,
        source=source,
        status="pending" if source == "keypoints" else "detecting",
        people=people,
        request_id=request_id,
    )


def _attach_inserted(session: Session, frame: Frame) -> None:
    """Attach an object whose row a Core insert wrote to the session as if loaded: no SELECT, no second INSERT."""
    make_transient_to_detached(frame)
    session.add(frame)


def add_image_frame(
    session: Session,
    camera: Camera,
    *,
    timestamp: datetime,
    content_type: str,
    width_px: int,
    height_px: int,
    data: bytes,
    client_frame_id: str | None = None,
    received_at: datetime | None = None,
    request_id: str | None = None,
) -> tuple[Frame, bool]:
    """Store an image frame, `detecting` until its pose job has run; returns (frame, created) like keypoint frames.

    The picture goes to `frame_images`, the pose job's input; `record_detections` deletes it afterwards unless
    the camera keeps images. A retry with the same client frame id stores nothing.
    """
    _check_timestamp(timestamp)
    if client_frame_id is not None:
        existing = _frame_by_client_id(session, camera.id, client_frame_id)
        if existing is not None:
            return existing, False
    frame = _new_frame(
        camera.id, timestamp, client_frame_id, received_at or utc_now(), source="image", request_id=request_id
    )
    image = {
        "frame_id": frame.id,
        "content_type": content_type,
        "width_px": width_px,
        "height_px": height_px,
        "data": data,
        "created_at": frame.received_at,
    }
    try:
        with session.begin_nested():
            session.execute(insert(_FRAMES), [_frame_row(frame)])
            session.execute(insert(FrameImage), [image])
    except IntegrityError:
        existing = None if client_frame_id is None else _frame_by_client_id(session, camera.id, client_frame_id)
        if existing is not None:
            return existing, False
        if session.get(Camera, camera.id) is None:
            raise CameraNotFoundError(camera.id) from None
        raise
    _attach_inserted(session, frame)
    return frame, True


def frame_image(session: Session, frame_id: uuid.UUID) -> FrameImage | None:
    return session.get(FrameImage, frame_id)


def frame_image_kept(session: Session, frame_id: uuid.UUID) -> bool:
    """Whether the frame's image is stored, without loading its bytes."""
    return session.scalar(select(func.count()).where(FrameImage.frame_id == frame_id)) == 1


def record_detections(
    session: Session, frame_id: uuid.UUID, people: Sequence[PersonIn], *, pose_model: str
) -> Frame | None:
    """Store what the pose model found in an image frame and make the frame `pending` (ready to measure).

    Only a frame still `detecting` is updated, so a pose job that runs twice (a retry after a crash) stores its
    people once; returns None when there was nothing to do. The image is then deleted unless the camera keeps
    images.
    """
    frame = session.get(Frame, frame_id)
    if frame is None or frame.status != "detecting":
        return None
    camera = existing_camera(session, frame.camera_id)
    claimed = session.execute(
        update(_FRAMES)
        .where(_FRAMES.c.id == frame_id, _FRAMES.c.status == "detecting")
        .values(status="pending", people=len(people), pose_model=pose_model)
    )
    if not claimed.rowcount:  # type: ignore[attr-defined]
        return None
    _insert_observations(session, camera.id, _observation_rows(camera, frame_id, people))
    if not camera.keep_images:
        session.execute(delete(FrameImage).where(FrameImage.frame_id == frame_id))
    session.expire_all()
    return session.get(Frame, frame_id)


def record_detection_failure(session: Session, frame_id: uuid.UUID, error: str) -> Frame | None:
    """An image frame whose picture could not be analysed: `failed` with the reason; its image is dropped unless
    the camera keeps images (then it stays for inspection)."""
    frame = session.get(Frame, frame_id)
    if frame is None or frame.status != "detecting":
        return None
    camera = existing_camera(session, frame.camera_id)
    frame.status, frame.error, frame.processed_at = "failed", clip_reason(error, FRAME_ERROR_MAX_LENGTH), utc_now()
    if not camera.keep_images:
        session.execute(delete(FrameImage).where(FrameImage.frame_id == frame_id))
    session.flush()
    return frame


def frames_detecting(session: Session) -> list[tuple[str, uuid.UUID]]:
    """(camera_id, frame_id) of image frames waiting for their pose job, oldest first (worker start-up)."""
    stmt = select(Frame.camera_id, Frame.id).where(Frame.status == "detecting").order_by(Frame.received_at, Frame.id)
    return [(camera_id, frame_id) for camera_id, frame_id in session.execute(stmt)]


def delete_kept_images(session: Session, camera_id: str) -> int:
    """Forget a camera's kept images (it stopped keeping them); images still awaiting pose stay until used."""
    done = select(Frame.id).where(Frame.camera_id == camera_id, Frame.status != "detecting")
    result = session.execute(delete(FrameImage).where(FrameImage.frame_id.in_(done)))
    return int(result.rowcount)  # type: ignore[attr-defined]


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
    """Several frames' people as light rows of their centres (`shoulder_x_px` ... `ankle_y_px`) and
    `unusable_reason` (the posture measuring reads), in posted order.

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
            columns.unusable_reason,
        )
        .where(columns.frame_id.in_(frame_ids))
        .order_by(columns.frame_id, columns.person_index)
    )
    for row in session.execute(stmt):
        people.setdefault(row.frame_id, []).append(row)
    return people


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
