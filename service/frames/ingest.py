"""Frames into the store (the frames repository's write path): posted keypoint frames, one at a time or a write
batch, image frames, and the people the pose job finds in them.

Functions flush but never commit: the caller owns the transaction. An idempotent frame insert that races with a retry
of itself runs inside a SAVEPOINT and resolves the unique-constraint collision by reading the winner's frame, so a
retry never fails and never stores its people twice. A frame checked against its camera's image size elsewhere (the
API keeps cameras in memory) is checked again here, in the transaction that stores it (see _current_sizes), and each
frame stores the digest of its content (service.frames.digests), so a client frame id reused with other content can
be told from a retry.
"""

from __future__ import annotations

import math
import random
import time
import uuid
from collections.abc import Collection, Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from datetime import datetime
from functools import cached_property
from typing import Any, cast

import numpy as np
from sqlalchemy import Table, bindparam, delete, insert, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, make_transient_to_detached

from service.cameras.repository import CameraNotFoundError, CameraResizedError, camera_counters, existing_camera
from service.domain import CameraCounters, PersonIn, Point
from service.frames.digests import keypoint_frame_digest
from service.geometry.evidence import grid_cells
from service.store.models import (
    FRAME_ERROR_MAX_LENGTH,
    Camera,
    Frame,
    FrameImage,
    Observation,
    clip_reason,
    pack_keypoints,
    utc_now,
)

# Bulk inserts go through the Core tables: ~15% less overhead per frame than ORM bulk inserts.
_OBSERVATIONS = cast(Table, Observation.__table__)
_FRAMES = cast(Table, Frame.__table__)
_CAMERAS = cast(Table, Camera.__table__)
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
    "content_sha256",
)


class FramesRefusedError(Exception):
    """Some frames of a batch cannot be stored (their camera was deleted or resized); nothing was written.

    `errors` maps positions in the batch to each refused frame's own error, so the caller stores the others.
    """

    def __init__(self, errors: dict[int, Exception]) -> None:
        super().__init__(f"{len(errors)} frames of the batch refused")
        self.errors = errors


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

    @cached_property
    def content_sha256(self) -> str:
        """The digest stored with the frame (keypoint_frame_digest), computed on first use: a stored frame's retry
        is compared with it; a new frame's digest comes from its packed rows instead."""
        return keypoint_frame_digest(self.timestamp, self.people)


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
                "appearance": person.appearance,
                "client_track_id": person.track_id,
                "usable": reason is None,
                "unusable_reason": None if reason is None else clip_reason(reason),
                "posture": person.posture,
                "placed_from_box": person.placed_from_box,
                "static": person.static,
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
    usable = sum(1 for row in rows if row["usable"])
    epoch = session.execute(_COUNT_EVIDENCE, {"camera": camera_id, "usable": usable}).scalar_one_or_none()
    _set_epochs(rows, {camera_id: epoch or 1})  # a camera deleted meanwhile: the foreign key refuses the rows
    session.execute(insert(_OBSERVATIONS), rows)


# The camera's calibration epoch is read by the statement that takes the camera row's lock (PostgreSQL re-reads a
# row another transaction changed before it updates it), so people stored while a move or a reset opens the next
# epoch (service.calibration.repository, which locks the same row) are never counted in one epoch and stored in
# another.
_COUNT_EVIDENCE = (
    update(_CAMERAS)
    .where(_CAMERAS.c.id == bindparam("camera"))
    .values(usable_evidence_count=_CAMERAS.c.usable_evidence_count + bindparam("usable"))
    .returning(_CAMERAS.c.epoch)
)
_INSERT_FRAMES = insert(_FRAMES)
_INSERT_OBSERVATIONS = insert(_OBSERVATIONS)


def _set_epochs(rows: Sequence[dict[str, Any]], epochs: dict[str, int]) -> None:
    """People join their camera's current calibration epoch."""
    for row in rows:
        row["epoch"] = epochs.get(row["camera_id"], 1)


_CURRENT_SIZES = (
    select(_CAMERAS.c.id, _CAMERAS.c.image_width_px, _CAMERAS.c.image_height_px)
    .where(_CAMERAS.c.id.in_(bindparam("ids", expanding=True)))
    .with_for_update(key_share=True)
)


def _current_sizes(session: Session, camera_ids: Collection[str]) -> dict[str, tuple[int, int]]:
    """The cameras' image sizes as this transaction will commit against them, by id (deleted cameras absent).

    Frames are checked against a camera read earlier (each API process keeps cameras in memory), so the store checks
    that size again here, and refuses a frame whose camera has been resized since: its people were checked against
    the old image and must not join the new one's evidence. On PostgreSQL the rows are locked (FOR NO KEY UPDATE)
    until commit, so a PUT resizing one of these cameras either committed before this read (and is seen) or waits
    for this commit (and then drops what it stored); on SQLite the writer already holds the one write lock.
    """
    if not camera_ids:
        return {}
    rows = session.execute(_CURRENT_SIZES, {"ids": sorted(camera_ids)})
    return {row.id: (row.image_width_px, row.image_height_px) for row in rows}


def _size_error(camera: Camera, sizes: dict[str, tuple[int, int]]) -> Exception | None:
    """Why a frame checked against `camera` cannot be stored now (see _current_sizes), or None."""
    size = sizes.get(camera.id)
    if size is None:
        return CameraNotFoundError(camera.id)
    if size != (camera.image_width_px, camera.image_height_px):
        return CameraResizedError(camera.id, size)
    return None


_COUNT_EVIDENCE_WHERE_UNCHANGED = (
    update(_CAMERAS)
    .where(
        _CAMERAS.c.id == bindparam("camera"),
        _CAMERAS.c.image_width_px == bindparam("width"),
        _CAMERAS.c.image_height_px == bindparam("height"),
    )
    .values(usable_evidence_count=_CAMERAS.c.usable_evidence_count + bindparam("usable"))
)


def _count_evidence_where_unchanged(
    session: Session, checked: dict[int, Camera], usable: dict[str, int]
) -> dict[int, Exception]:
    """Add a batch's usable people to their cameras' counters, on the cameras still of the size the frames were
    checked against; returns the errors of the frames that cannot be stored (camera deleted or resized).

    The counters' update, which the batch makes anyway, is the size check at commit (see _current_sizes for why it
    must happen in the storing transaction, and why it orders this transaction with a resize on PostgreSQL): one
    pre-built statement, run once per camera in id order (one lock order for every writer), and only when it
    updates fewer rows than it was given are the sizes read, to say which frames are refused. A statement of its
    own to read the sizes cost about 120 us per batch on SQLite, half the cost of storing a frame's people when
    light load makes batches of one frame. A refused frame rolls the caller's transaction back with the counters,
    and the batch is stored again without it.
    """
    if not checked:
        return {}
    expected = sorted({(camera.id, camera.image_width_px, camera.image_height_px) for camera in checked.values()})
    rows = [
        {"camera": camera_id, "width": width, "height": height, "usable": usable.get(camera_id, 0)}
        for camera_id, width, height in expected
    ]
    if session.connection().execute(_COUNT_EVIDENCE_WHERE_UNCHANGED, rows).rowcount == len(rows):
        return {}
    current = _current_sizes(session, {camera.id for camera in checked.values()})
    return {i: error for i, camera in checked.items() if (error := _size_error(camera, current)) is not None}


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
    the stored frame with created=False and stores nothing, so evidence is never counted twice (whether the
    content is the same is the caller's question: compare `content_sha256`). `camera`, when the caller has already
    read it (the API, from memory), is the camera the people were checked against: a camera deleted or resized
    since raises CameraNotFoundError or CameraResizedError. `request_id` is the posting request's id, kept so the
    jobs that handle the frame log under it.
    """
    _check_timestamp(timestamp)
    checked_elsewhere = camera is not None
    if camera is None:
        camera = existing_camera(session, camera_id)  # read in this transaction: current by construction
    if client_frame_id is not None:
        existing = _frame_by_client_id(session, camera_id, client_frame_id)
        if existing is not None:
            return existing, False
    refused = _size_error(camera, _current_sizes(session, [camera_id])) if checked_elsewhere else None
    if refused is not None:
        raise refused
    # The rows go in as Core inserts, which cost a fraction of an ORM flush.
    frame = _new_frame(
        camera_id, timestamp, client_frame_id, received_at or utc_now(), people=len(people), request_id=request_id
    )
    rows = _observation_rows(camera, frame.id, people)
    frame.content_sha256 = keypoint_frame_digest(timestamp, people, [row["keypoints_f32"] for row in rows])
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


@dataclass(frozen=True)
class PreparedKeypointFrame:
    """A new keypoint frame's rows, built before its transaction (prepare_keypoint_frames).

    On SQLite the storing transaction holds the database's one write lock from its first statement, and every other
    writer (the other API processes, the workers) waits for it meanwhile: building the rows there held the lock about
    twice as long as the statements need.
    """

    item: NewKeypointFrame
    frame: Frame
    """The frame as it will be inserted if it is new (its id is drawn here; a retry's prepared frame is dropped)."""
    frame_row: dict[str, Any]
    observation_rows: list[dict[str, Any]]
    usable: int


def prepare_keypoint_frame(item: NewKeypointFrame, *, received_at: datetime) -> PreparedKeypointFrame:
    """The rows the frame would insert, with no session: raises ValueError for a frame the store cannot take."""
    _check_timestamp(item.timestamp)
    frame = _new_frame(
        item.camera.id,
        item.timestamp,
        item.client_frame_id,
        received_at,
        people=len(item.people),
        request_id=item.request_id,
    )
    rows = _observation_rows(item.camera, frame.id, item.people)
    frame.content_sha256 = keypoint_frame_digest(item.timestamp, item.people, [row["keypoints_f32"] for row in rows])
    usable = sum(1 for row in rows if row["usable"])
    return PreparedKeypointFrame(item, frame, _frame_row(frame), rows, usable)


def add_keypoint_frames(
    session: Session,
    frames: Sequence[PreparedKeypointFrame],
    counters: dict[str, CameraCounters] | None = None,
) -> list[tuple[Frame, bool]]:
    """Store several prepared frames and their people with one statement per table; returns (frame, created) per
    frame. `counters`, when given, receives the evidence counters of the cameras whose people were stored, as this
    transaction leaves them (read with their epochs, so the writer's after-commit step needs no read of its own).

    The API's group commit (service.frames.writer) writes the frames that arrive while the previous batch
    is being written in one transaction, which costs a fraction of one transaction per frame. Retries are
    answered as in add_keypoint_frame: a client frame id already stored, or repeated within the batch, returns
    the first frame with created=False. New frames whose camera was deleted or resized since it was read raise
    FramesRefusedError naming them, before anything is written, so the caller stores the others (the evidence
    counters' update is that check: see _count_evidence_where_unchanged). There is no SAVEPOINT per frame: a frame
    whose client id another process stored since the check makes the whole batch raise IntegrityError, and the
    caller stores those frames one at a time instead. A prepared frame may be given again after its transaction
    rolled back.
    """
    known = _frames_by_client_ids(session, [prepared.item for prepared in frames])
    results: list[tuple[Frame, bool]] = []
    frame_rows: list[dict[str, Any]] = []
    observation_rows: list[dict[str, Any]] = []
    usable: dict[str, int] = {}
    checked: dict[int, Camera] = {}  # position of each new frame -> the camera it was checked against
    for position, prepared in enumerate(frames):
        item, frame = prepared.item, prepared.frame
        camera_id = item.camera.id
        key = (camera_id, item.client_frame_id)
        if item.client_frame_id is not None:
            if key in known:
                results.append((known[key], False))
                continue
            known[key] = frame
        frame_rows.append(prepared.frame_row)
        observation_rows += prepared.observation_rows
        usable[camera_id] = usable.get(camera_id, 0) + prepared.usable
        checked[position] = item.camera
        results.append((frame, True))
    refused = _count_evidence_where_unchanged(session, checked, usable)
    if refused:
        raise FramesRefusedError(refused)
    # Core statements on the session's connection: the same transaction, without the ORM's execution path (~40 us
    # a statement, four a batch).
    connection = session.connection()
    if frame_rows:
        connection.execute(_INSERT_FRAMES, frame_rows)
    if observation_rows:
        # After the counters' update, which holds the cameras' rows until commit: their epochs cannot change now.
        now = camera_counters(connection, usable)
        _set_epochs(observation_rows, {camera_id: state.epoch for camera_id, state in now.items()})
        connection.execute(_INSERT_OBSERVATIONS, observation_rows)
        if counters is not None:
            counters.update(now)
    for frame, created in results:
        if created:
            _attach_inserted(session, frame)
    return results


def _frames_by_client_ids(session: Session, frames: Sequence[NewKeypointFrame]) -> dict[tuple[str, str | None], Frame]:
    """Stored frames among the batch's client frame ids, by (camera id, client frame id): one query for the whole
    batch, of one shape whatever the batch, so it is compiled once (an OR of one IN per camera was compiled anew for
    most batches: 300 against 85 us). The batch's cameras crossed with its client ids are looked up on the
    (camera_id, client_frame_id) index: a superset of the pairs wanted, whose extra frames no lookup asks for (a
    row-value IN would say it exactly, and SQLite answers it by scanning the table)."""
    cameras = sorted({item.camera.id for item in frames if item.client_frame_id is not None})
    if not cameras:
        return {}
    client_ids = sorted({item.client_frame_id for item in frames if item.client_frame_id is not None})
    stored = session.connection().execute(_STORED_CLIENT_IDS, {"cameras": cameras, "client_ids": client_ids}).all()
    # A stored id is a retry, rare: its frame is loaded then (gone since, it is new again).
    frames_by_key = {(row.camera_id, row.client_frame_id): session.get(Frame, row.id) for row in stored}
    return {key: frame for key, frame in frames_by_key.items() if frame is not None}


_STORED_CLIENT_IDS = select(_FRAMES.c.id, _FRAMES.c.camera_id, _FRAMES.c.client_frame_id).where(
    _FRAMES.c.camera_id.in_(bindparam("cameras", expanding=True)),
    _FRAMES.c.client_frame_id.in_(bindparam("client_ids", expanding=True)),
)


def _check_timestamp(timestamp: datetime) -> None:
    if timestamp.tzinfo is None or timestamp.utcoffset() is None:
        raise ValueError(f"timestamp {timestamp!r} has no timezone: the store keeps UTC instants")


def new_frame_id() -> uuid.UUID:
    """A UUIDv7 (RFC 9562): the Unix time in milliseconds, then 74 random bits.

    Not the uuid6 package's: it draws the random bits from `secrets`, which reads os.urandom, a system call that
    releases the GIL, and the frame writer's thread then waits for the event loop to give it back, up to the 5 ms
    switch interval, once per frame (a tenth of the writer's time under `posemetry bench ingest`). An id needs
    uniqueness, not secrecy: `random` is seeded from the OS, and again in each forked process."""
    value = (time.time_ns() // 1_000_000 & 0xFFFF_FFFF_FFFF) << 80 | random.getrandbits(80)
    value = value & ~(0xF << 76) | 0x7 << 76  # version 7
    value = value & ~(0x3 << 62) | 0x2 << 62  # the RFC's variant
    return uuid.UUID(int=value)


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
        id=new_frame_id(),
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
    content_sha256: str | None = None,
) -> tuple[Frame, bool]:
    """Store an image frame, `detecting` until its pose job has run; returns (frame, created) like keypoint frames.

    The picture goes to `frame_images`, the pose job's input; `record_detections` deletes it afterwards unless
    the camera keeps images. A retry with the same client frame id stores nothing. `camera` is the camera the
    image was checked against: CameraResizedError if its size has changed since (see _current_sizes).
    `content_sha256` is image_frame_digest of what was posted.
    """
    _check_timestamp(timestamp)
    if client_frame_id is not None:
        existing = _frame_by_client_id(session, camera.id, client_frame_id)
        if existing is not None:
            return existing, False
    refused = _size_error(camera, _current_sizes(session, [camera.id]))
    if refused is not None:
        raise refused
    frame = _new_frame(
        camera.id, timestamp, client_frame_id, received_at or utc_now(), source="image", request_id=request_id
    )
    frame.content_sha256 = content_sha256
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
