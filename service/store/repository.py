"""Every database operation the API and the workers perform, one small function each, taking a Session.

Functions flush but never commit: the caller owns the transaction, so a route or a job can combine several
operations (store a result and its violation events, say) atomically. Functions that may race with themselves
across processes (camera upsert, idempotent frame insert) run their insert inside a SAVEPOINT and resolve a
unique-constraint collision by reading the winner's row, so a retry never fails and never duplicates.
"""

from __future__ import annotations

import hashlib
import math
import random
import struct
import uuid
from collections.abc import Collection, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from functools import cached_property
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import uuid6
from sqlalchemy import (
    BigInteger,
    ColumnElement,
    Row,
    Select,
    Table,
    Text,
    and_,
    bindparam,
    delete,
    func,
    insert,
    literal,
    or_,
    select,
    true,
    union_all,
    update,
)
from sqlalchemy import cast as sa_cast
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, defer, make_transient_to_detached

from .models import (
    CALIBRATION_STATUSES,
    DEFAULT_DISTANCE_THRESHOLD_M,
    FRAME_ERROR_MAX_LENGTH,
    FRAME_STATUSES,
    GRID_CELLS,
    GRID_COLS,
    GRID_ROWS,
    SAMPLE_KEY_SPACE,
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

if TYPE_CHECKING:
    from service.geometry import Calibration

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
_VIOLATION_EVENTS = cast(Table, ViolationEvent.__table__)

MINUTE_S = 60
HOUR_S = 3600

Point = tuple[float, float]


class CameraNotFoundError(LookupError):
    """The camera id is not configured (the API answers 404)."""


class FrameNotFoundError(LookupError):
    """No frame with that id (for that camera)."""


class CameraResizedError(Exception):
    """The camera's image size is no longer the one its frame was checked against (a PUT changed it since): the
    frame is not stored, so no person checked against the old size joins the new size's evidence."""

    def __init__(self, camera_id: str, size_px: tuple[int, int]) -> None:
        super().__init__(f"camera {camera_id!r} is now {size_px[0]}x{size_px[1]} px")
        self.camera_id = camera_id
        self.size_px = size_px


class FramesRefusedError(Exception):
    """Some frames of a batch cannot be stored (their camera was deleted or resized); nothing was written.

    `errors` maps positions in the batch to each refused frame's own error, so the caller stores the others.
    """

    def __init__(self, errors: dict[int, Exception]) -> None:
        super().__init__(f"{len(errors)} frames of the batch refused")
        self.errors = errors


# --------------------------------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class PersonIn:
    """One person of a posted frame, already reduced to the two points the geometry uses.

    `unusable_reason` is the caller's verdict on evidence quality (low keypoint scores, say); a person whose
    shoulder or ankle centre is missing is never usable, and the store records why.
    """

    shoulder_px: Point | None
    ankle_px: Point | None
    keypoints: Sequence[Sequence[float]] | None = None
    unusable_reason: str | None = None
    box_px: tuple[float, float, float, float] | None = None
    """Detector box (left, top, right, bottom) of a person found in an image."""
    detection_score: float | None = None


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


@dataclass(frozen=True)
class CalibrationValues:
    """What one solve produced, in the store's units; build it with from_solution or failure."""

    status: str
    person_height_m: float
    people_used: int
    inliers: int
    evidence_count: int
    reason: str | None = None
    fx_px: float | None = None
    fy_px: float | None = None
    cx_px: float | None = None
    cy_px: float | None = None
    normal: tuple[float, float, float] | None = None
    rho_m: float | None = None
    fx_std_px: float | None = None
    fy_std_px: float | None = None
    normal_std_deg: float | None = None
    rho_std_m: float | None = None
    covariance: Sequence[Sequence[float]] | None = None
    noise_px: float | None = None
    distortion_k: float | None = None
    duration_s: float | None = None

    @classmethod
    def from_solution(
        cls, cal: Calibration, *, people_used: int, evidence_count: int, duration_s: float | None = None
    ) -> CalibrationValues:
        """The storable part of a service.geometry Calibration (per-person arrays are not kept)."""
        unc = cal.uncertainty
        normal = tuple(float(v) for v in cal.normal)
        return cls(
            status="ok",
            person_height_m=float(cal.height_m),
            people_used=people_used,
            inliers=cal.num_inliers,
            evidence_count=evidence_count,
            fx_px=float(cal.fx),
            fy_px=float(cal.fy),
            cx_px=float(cal.cx),
            cy_px=float(cal.cy),
            normal=(normal[0], normal[1], normal[2]),
            rho_m=float(cal.rho),
            fx_std_px=None if unc is None else float(unc.fx_px),
            fy_std_px=None if unc is None else float(unc.fy_px),
            normal_std_deg=None if unc is None else float(unc.normal_deg),
            rho_std_m=None if unc is None else float(unc.rho_m),
            covariance=None if unc is None else np.asarray(unc.covariance, dtype=float).tolist(),
            noise_px=None if unc is None else float(unc.noise_px),
            distortion_k=float(cal.distortion_k),
            duration_s=duration_s,
        )

    @classmethod
    def failure(
        cls,
        reason: str,
        *,
        person_height_m: float,
        people_used: int,
        evidence_count: int,
        duration_s: float | None = None,
    ) -> CalibrationValues:
        """A solve that produced no camera, kept in the history so operators can see why."""
        return cls(
            status="failed",
            reason=reason,
            person_height_m=person_height_m,
            people_used=people_used,
            inliers=0,
            evidence_count=evidence_count,
            duration_s=duration_s,
        )


@dataclass(frozen=True)
class ViolationIn:
    """A pair of people (indices into the frame's people) closer than the camera's threshold."""

    person_i: int
    person_j: int
    distance_m: float
    distance_std_m: float | None = None


# --------------------------------------------------------------------------------------------------- outputs


@dataclass(frozen=True)
class FrameOutcome:
    """A measured frame as the worker stores it: `done` with a result and violations, or `failed` with a reason."""

    frame_id: uuid.UUID
    camera_id: str
    timestamp: datetime
    status: str
    calibration_version: int | None
    result: Any = None
    """The result as a JSON-ready dict, or already encoded (`service.store.db.EncodedJSON`)."""
    violations: Sequence[ViolationIn] = ()
    error: str | None = None


@dataclass(frozen=True)
class EvidenceSample:
    """A calibration's input: shoulder/ankle centres of a balanced sample of usable observations.

    `queries` and `rows_read` show the cost: rows_read stays near len(self) however much is stored.
    """

    observation_ids: list[int]
    cells: list[int]
    tops_px: np.ndarray
    bottoms_px: np.ndarray
    queries: int = 0
    rows_read: int = 0

    def __len__(self) -> int:
        return len(self.observation_ids)


@dataclass(frozen=True)
class ViolationBucket:
    """Violations whose timestamp falls in [start, start + width)."""

    start: datetime
    count: int


# --------------------------------------------------------------------------------------------------- helpers


def _finite_or_none(value: float | None) -> float | None:
    """NaN/inf become NULL: SQLite silently stores NaN as NULL anyway, and PostgreSQL JSON rejects it."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _check_point(name: str, point: Point | None) -> None:
    if point is not None and not (len(point) == 2 and all(math.isfinite(float(v)) for v in point)):
        raise ValueError(f"{name} must be two finite pixel coordinates, got {point!r}")


# What "the same content" means for a client frame id (README, Idempotency): the same instant to the microsecond and
# the same people in the same order, each as stored: keypoints at the float32 precision they are packed with,
# centres as float64. How the JSON spelled the numbers (1 or 1.0, 1e2 or 100) and the key order do not matter.
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_CENTRES = struct.Struct("<?dd?dd")


def _instant_bytes(timestamp: datetime) -> bytes:
    return ((timestamp - _EPOCH) // timedelta(microseconds=1)).to_bytes(8, "little", signed=True)


def keypoint_frame_digest(
    timestamp: datetime, people: Sequence[PersonIn], packed: Sequence[bytes | None] | None = None
) -> str:
    """SHA-256 (hex) of a keypoint frame's content; `packed` is each person's packed keypoints if already made."""
    digest = hashlib.sha256(b"posemetry keypoint frame v1\0")
    digest.update(_instant_bytes(timestamp))
    digest.update(len(people).to_bytes(4, "little"))
    for index, person in enumerate(people):
        if person.keypoints is not None:
            digest.update(b"k")
            digest.update(packed[index] if packed is not None else pack_keypoints(person.keypoints))  # type: ignore[arg-type]
        else:
            shoulder, ankle = person.shoulder_px, person.ankle_px
            digest.update(b"c")
            digest.update(
                _CENTRES.pack(
                    shoulder is not None,
                    *(shoulder or (0.0, 0.0)),
                    ankle is not None,
                    *(ankle or (0.0, 0.0)),
                )
            )
    return digest.hexdigest()


def image_frame_digest(data: bytes) -> str:
    """SHA-256 (hex) of an image frame's bytes. Its timestamp is compared apart, and only when a retry gives one:
    a frame posted without one is stamped with its time of receipt, which no retry can repeat."""
    return hashlib.sha256(b"posemetry image frame v1\0" + data).hexdigest()


def grid_cell(x_px: float, y_px: float, width_px: int, height_px: int) -> int:
    """The sampling-grid cell of an image point; points slightly outside the image go to the edge cell."""
    col = min(max(math.floor(x_px / width_px * GRID_COLS), 0), GRID_COLS - 1)
    row = min(max(math.floor(y_px / height_px * GRID_ROWS), 0), GRID_ROWS - 1)
    return row * GRID_COLS + col


# Fibonacci hashing of the observation id: the odd multiplier (2^32 / golden ratio) makes it a bijection on
# [0, SAMPLE_KEY_SPACE), so ids below 2^31 never tie, and consecutive ids (one frame's people, one camera's
# minutes) land far apart and evenly over the key space, so a range of keys samples evenly over time. Computed by
# the database (products stay below 2^63 on both backends); `sample_key` is the same function in Python.
_KEY_MULTIPLIER = 2654435761


def sample_key(observation_id: int) -> int:
    return (observation_id % SAMPLE_KEY_SPACE) * _KEY_MULTIPLIER % SAMPLE_KEY_SPACE


def _sample_key_sql(observation_id: ColumnElement[int]) -> ColumnElement[int]:
    space, multiplier = literal(SAMPLE_KEY_SPACE, BigInteger), literal(_KEY_MULTIPLIER, BigInteger)
    return (observation_id % space) * multiplier % space


def _require_camera(session: Session, camera_id: str, *, for_update: bool = False) -> Camera:
    stmt = select(Camera).where(Camera.id == camera_id).execution_options(populate_existing=True)
    if for_update:
        stmt = stmt.with_for_update()
    camera = session.execute(stmt).scalar_one_or_none()
    if camera is None:
        raise CameraNotFoundError(camera_id)
    return camera


# --------------------------------------------------------------------------------------------------- cameras


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
    now: datetime | None = None,
) -> tuple[Camera, bool]:
    """Create or update a camera's settings; returns (camera, created) so PUT can answer 201 or 200.

    person_height_m has no default here: the API owns the default (service.geometry.DEFAULT_HEIGHT_M).

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
    }
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


# --------------------------------------------------------------------------------------------------- frames


def _observation_rows(camera: Camera, frame_id: uuid.UUID, people: Sequence[PersonIn]) -> list[dict[str, Any]]:
    rows = []
    for index, person in enumerate(people):
        _check_point("shoulder_px", person.shoulder_px)
        _check_point("ankle_px", person.ankle_px)
        reason = person.unusable_reason
        if reason is None and person.shoulder_px is None:
            reason = "shoulder centre not visible"
        if reason is None and person.ankle_px is None:
            reason = "ankle centre not visible"
        shoulder = person.shoulder_px or (None, None)
        ankle = person.ankle_px or (None, None)
        box = person.box_px or (None, None, None, None)
        cell = None
        if person.ankle_px is not None:
            cell = grid_cell(person.ankle_px[0], person.ankle_px[1], camera.image_width_px, camera.image_height_px)
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
    if session.execute(_COUNT_EVIDENCE_WHERE_UNCHANGED, rows).rowcount == len(rows):  # type: ignore[attr-defined]
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
        camera = _require_camera(session, camera_id)  # read in this transaction: current by construction
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


def add_keypoint_frames(
    session: Session, frames: Sequence[NewKeypointFrame], *, received_at: datetime | None = None
) -> list[tuple[Frame, bool]]:
    """Store several frames and their people with one statement per table; returns (frame, created) per frame.

    The API's group commit (service.store.frame_writer) writes the frames that arrive while the previous batch
    is being written in one transaction, which costs a fraction of one transaction per frame. Retries are
    answered as in add_keypoint_frame: a client frame id already stored, or repeated within the batch, returns
    the first frame with created=False. New frames whose camera was deleted or resized since it was read raise
    FramesRefusedError naming them, before anything is written, so the caller stores the others (the evidence
    counters' update is that check: see _count_evidence_where_unchanged). There is no SAVEPOINT per frame: a frame
    whose client id another process stored since the check makes the whole batch raise IntegrityError, and the
    caller stores those frames one at a time instead.
    """
    received_at = received_at or utc_now()
    for item in frames:
        _check_timestamp(item.timestamp)
    known = _frames_by_client_ids(session, frames)
    results: list[tuple[Frame, bool]] = []
    frame_rows: list[dict[str, Any]] = []
    observation_rows: list[dict[str, Any]] = []
    usable: dict[str, int] = {}
    checked: dict[int, Camera] = {}  # position of each new frame -> the camera it was checked against
    for position, item in enumerate(frames):
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
        frame.content_sha256 = keypoint_frame_digest(item.timestamp, item.people, [r["keypoints_f32"] for r in rows])
        frame_rows.append(_frame_row(frame))
        observation_rows += rows
        usable[camera_id] = usable.get(camera_id, 0) + sum(1 for row in rows if row["usable"])
        checked[position] = item.camera
        results.append((frame, True))
    refused = _count_evidence_where_unchanged(session, checked, usable)
    if refused:
        raise FramesRefusedError(refused)
    if frame_rows:
        session.execute(insert(_FRAMES), frame_rows)
    if observation_rows:
        session.execute(insert(_OBSERVATIONS), observation_rows)
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
    camera = _require_camera(session, frame.camera_id)
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
    camera = _require_camera(session, frame.camera_id)
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
    """Several frames' people as light rows of their centres (`shoulder_x_px` ... `ankle_y_px`), posted order.

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


def set_frame_result(
    session: Session,
    frame_id: uuid.UUID,
    *,
    status: str,
    result: dict[str, Any] | None = None,
    calibration_version: int | None = None,
    error: str | None = None,
    now: datetime | None = None,
) -> Frame:
    """Record a frame's outcome; recomputing a frame (after a newer calibration) overwrites the previous one."""
    if status not in FRAME_STATUSES:
        raise ValueError(f"status must be one of {FRAME_STATUSES}, got {status!r}")
    frame = session.get(Frame, frame_id)
    if frame is None:
        raise FrameNotFoundError(str(frame_id))
    frame.status = status
    frame.result = result
    frame.calibration_version = calibration_version
    frame.error = error
    frame.processed_at = None if status == "pending" else (now or utc_now())
    session.flush()
    return frame


# --------------------------------------------------------------------------------------------------- evidence


def usable_evidence_count(session: Session, camera_id: str) -> int:
    """Usable observations stored for the camera, from the counter kept on insert (O(1))."""
    count = session.execute(select(Camera.usable_evidence_count).where(Camera.id == camera_id)).scalar_one_or_none()
    if count is None:
        raise CameraNotFoundError(camera_id)
    return int(count)


def evidence_for_next_solve(camera: Camera, *, min_people: int, growth_factor: float) -> int:
    """Usable evidence at which the next solve is due: min_people first, then growth_factor x the last solve's."""
    if camera.evidence_at_last_solve <= 0:
        return min_people
    return max(min_people, math.ceil(growth_factor * camera.evidence_at_last_solve))


def calibration_due(camera: Camera, *, min_people: int, growth_factor: float) -> bool:
    """Whether evidence warrants a solve: a first one at min_people, then each time it grows by growth_factor."""
    target = evidence_for_next_solve(camera, min_people=min_people, growth_factor=growth_factor)
    return camera.usable_evidence_count >= target


def key_new_evidence(session: Session, camera_id: str, *, limit: int) -> int:
    """Give up to `limit` of the camera's unkeyed people their sample keys, oldest first; returns how many.

    Keying in bulk is what keeps ingest cheap: the sampling index is random in (cell, sample_key), so one person
    per insert dirtied one index page per person, while thousands at once share pages. Callers loop over short
    transactions until this returns less than `limit`, so ingest never waits long for the write lock.
    """
    if limit < 1:
        raise ValueError(f"limit must be positive, got {limit}")
    oldest = (
        select(_OBSERVATIONS.c.id)
        .where(_OBSERVATIONS.c.camera_id == camera_id, _OBSERVATIONS.c.sample_key.is_(None))
        .order_by(_OBSERVATIONS.c.id)
        .limit(limit)
    )
    result = session.execute(
        update(_OBSERVATIONS)
        .where(_OBSERVATIONS.c.id.in_(oldest.scalar_subquery()))
        .values(sample_key=_sample_key_sql(_OBSERVATIONS.c.id))
    )
    return int(result.rowcount)  # type: ignore[attr-defined]


@dataclass
class _CellCursor:
    """Where reading one cell in sample_key order resumes: keys >= start first, then wrapping to [0, start)."""

    start: int
    wrapped: bool = False
    last: tuple[int, int] | None = None  # (sample_key, id) of the last row read
    rows: list[Any] = field(default_factory=list)


_SAMPLE_COLUMNS = (
    Observation.id,
    Observation.cell,
    Observation.sample_key,
    Observation.shoulder_x_px,
    Observation.shoulder_y_px,
    Observation.ankle_x_px,
    Observation.ankle_y_px,
)


def _cell_page(camera_id: str, cell: int, cursor: _CellCursor, n: int) -> Select[*tuple[Any, ...]]:
    """The next n rows of one cell: an index range scan on (camera_id, usable, cell, sample_key)."""
    key, oid = Observation.sample_key, Observation.id
    conditions = [
        Observation.camera_id == camera_id,
        Observation.usable == true(),
        Observation.cell == cell,
        key.is_not(None),  # the partial index holds keyed people only
    ]
    if cursor.wrapped:
        conditions.append(key < cursor.start)
    if cursor.last is not None:
        last_key, last_id = cursor.last
        # The plain bound lets both backends start the index scan at last_key; the OR breaks key ties by id.
        conditions += [key >= last_key, (key > last_key) | (oid > last_id)]
    elif not cursor.wrapped:
        conditions.append(key >= cursor.start)
    return select(*_SAMPLE_COLUMNS).where(*conditions).order_by(key, oid).limit(n)


def sample_evidence(session: Session, camera_id: str, *, cap: int, seed: int = 0) -> EvidenceSample:
    """At most `cap` usable observations, spread as evenly over the image grid as the data allow.

    Round-robin over grid cells: every cell contributes equally, and cells with fewer people than their share
    give the remainder to the others (water-filling). Within a cell the order is the stored pseudo-random
    sample_key, read from a seed-dependent start, so a sample is random, reproducible for a given seed, and
    differs between seeds. The work is O(cap + cells) rows, whatever is stored: each round is one statement, a
    UNION ALL of one LIMITed index range scan per cell that is still short of the current level (per-cell LIMIT
    subqueries are the only "top n per group" that SQLite and PostgreSQL both run without reading every row;
    window functions and LATERAL do not qualify). Typically two to four rounds.
    """
    if cap < 1:
        raise ValueError(f"cap must be positive, got {cap}")
    rng = random.Random(seed)
    start = rng.randrange(SAMPLE_KEY_SPACE)
    cell_order = list(range(GRID_CELLS))
    rng.shuffle(cell_order)
    cursors = {cell: _CellCursor(start) for cell in range(GRID_CELLS)}
    active = set(cursors)
    level = queries = rows_read = 0
    while active:
        wanted = {cell: level - len(cursors[cell].rows) for cell in active if len(cursors[cell].rows) < level}
        if not wanted:
            total = sum(len(c.rows) for c in cursors.values())
            if total >= cap:
                break
            level += -(-(cap - total) // len(active))
            wanted = {cell: level - len(cursors[cell].rows) for cell in active}
        pages = [_cell_page(camera_id, cell, cursors[cell], n) for cell, n in sorted(wanted.items())]
        stmt = pages[0] if len(pages) == 1 else union_all(*(page.subquery().select() for page in pages))
        rows = session.execute(stmt).all()
        queries += 1
        rows_read += len(rows)
        by_cell: dict[int, list[Any]] = {cell: [] for cell in wanted}
        for row in rows:
            by_cell[row.cell].append(row)
        for cell, n in wanted.items():
            cursor, got = cursors[cell], sorted(by_cell[cell], key=lambda r: (r.sample_key, r.id))
            cursor.rows.extend(got)
            if got:
                cursor.last = (got[-1].sample_key, got[-1].id)
            if len(got) < n:
                if cursor.wrapped:
                    active.discard(cell)
                else:
                    cursor.wrapped, cursor.last = True, None
    chosen: list[Any] = []
    for rank in range(level):
        for cell in cell_order:
            if len(chosen) == cap:
                break
            if rank < len(cursors[cell].rows):
                chosen.append(cursors[cell].rows[rank])
    tops = np.array([(r.shoulder_x_px, r.shoulder_y_px) for r in chosen], dtype=float).reshape(-1, 2)
    bottoms = np.array([(r.ankle_x_px, r.ankle_y_px) for r in chosen], dtype=float).reshape(-1, 2)
    return EvidenceSample(
        observation_ids=[int(r.id) for r in chosen],
        cells=[int(r.cell) for r in chosen],
        tops_px=tops,
        bottoms_px=bottoms,
        queries=queries,
        rows_read=rows_read,
    )


# --------------------------------------------------------------------------------------------------- calibrations


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
    camera = _require_camera(session, camera_id, for_update=True)
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
        covariance = [[_finite_or_none(v) for v in row] for row in values.covariance]
    record = CalibrationVersion(
        camera_id=camera_id,
        version=(last or 0) + 1,
        status=values.status,
        reason=values.reason,
        fx_px=_finite_or_none(values.fx_px),
        fy_px=_finite_or_none(values.fy_px),
        cx_px=_finite_or_none(values.cx_px),
        cy_px=_finite_or_none(values.cy_px),
        normal_x=_finite_or_none(normal[0]),
        normal_y=_finite_or_none(normal[1]),
        normal_z=_finite_or_none(normal[2]),
        rho_m=_finite_or_none(values.rho_m),
        fx_std_px=_finite_or_none(values.fx_std_px),
        fy_std_px=_finite_or_none(values.fy_std_px),
        normal_std_deg=_finite_or_none(values.normal_std_deg),
        rho_std_m=_finite_or_none(values.rho_std_m),
        covariance=covariance,
        noise_px=_finite_or_none(values.noise_px),
        distortion_k=_finite_or_none(values.distortion_k),
        person_height_m=values.person_height_m,
        people_used=values.people_used,
        inliers=values.inliers,
        evidence_count=values.evidence_count,
        is_current=make_current,
        forced=forced,
        duration_s=_finite_or_none(values.duration_s),
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
    camera = _require_camera(session, camera_id, for_update=True)
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


# --------------------------------------------------------------------------------------------------- violations


def _violation_rows(
    camera_id: str, frame_id: uuid.UUID, timestamp: datetime, violations: Sequence[ViolationIn]
) -> list[dict[str, Any]]:
    epoch_s = math.floor(timestamp.timestamp())
    rows = []
    for v in violations:
        i, j = sorted((int(v.person_i), int(v.person_j)))
        if i == j or i < 0:
            raise ValueError(f"a violation needs two different people, got ({v.person_i}, {v.person_j})")
        rows.append(
            {
                "camera_id": camera_id,
                "frame_id": frame_id,
                "timestamp": timestamp,
                "epoch_s": epoch_s,
                "person_i": i,
                "person_j": j,
                "distance_m": float(v.distance_m),
                "distance_std_m": _finite_or_none(v.distance_std_m),
            }
        )
    return rows


def record_violations(session: Session, frame: Frame, violations: Sequence[ViolationIn]) -> int:
    """Replace the frame's violation events with these (a recomputed frame must not count twice)."""
    rows = _violation_rows(frame.camera_id, frame.id, frame.timestamp, violations)
    session.execute(delete(ViolationEvent).where(ViolationEvent.frame_id == frame.id))
    if rows:
        session.execute(insert(_VIOLATION_EVENTS), rows)
    return len(rows)


def record_frame_outcomes(session: Session, outcomes: Sequence[FrameOutcome], *, now: datetime | None = None) -> int:
    """Store many frames' results and replace their violation events, in a few statements (a worker's batch).

    Returns how many frames were updated; a frame deleted meanwhile (its camera was) is simply not among them.
    """
    if not outcomes:
        return 0
    now = now or utc_now()
    violation_rows = []
    for outcome in outcomes:
        if outcome.status not in ("done", "failed"):
            raise ValueError(f"an outcome is done or failed, got {outcome.status!r}")
        violation_rows += _violation_rows(outcome.camera_id, outcome.frame_id, outcome.timestamp, outcome.violations)
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
    if violation_rows:
        live = set(session.scalars(select(Frame.id).where(Frame.id.in_(frame_ids))))
        violation_rows = [row for row in violation_rows if row["frame_id"] in live]
    if violation_rows:
        session.execute(insert(_VIOLATION_EVENTS), violation_rows)
    session.expire_all()
    return int(updated.rowcount)  # type: ignore[attr-defined]


@dataclass(frozen=True)
class ViolationPlace:
    """A violation event with where its two people stood on the ground (metres, the frame result's `ground_m`)."""

    timestamp: datetime
    ground_i_m: tuple[float, float]
    ground_j_m: tuple[float, float]


def violation_places(
    session: Session, camera_id: str, *, since: datetime, until: datetime, limit: int
) -> list[ViolationPlace]:
    """The newest `limit` violation events in [since, until) with their people's ground positions.

    Positions come from the frames' stored results (one read per frame, not per event); an event whose frame
    has no position for either person (re-measured meanwhile, say) is left out.
    """
    events = session.execute(
        select(ViolationEvent.frame_id, ViolationEvent.timestamp, ViolationEvent.person_i, ViolationEvent.person_j)
        .where(
            ViolationEvent.camera_id == camera_id,
            ViolationEvent.epoch_s >= math.floor(since.timestamp()),
            ViolationEvent.epoch_s < math.floor(until.timestamp()),
        )
        .order_by(ViolationEvent.epoch_s.desc(), ViolationEvent.id.desc())
        .limit(limit)
    ).all()
    positions: dict[uuid.UUID, dict[int, tuple[float, float]]] = {}
    frame_ids = list({event.frame_id for event in events})
    for start in range(0, len(frame_ids), 500):
        chunk = frame_ids[start : start + 500]
        for frame_id, result in session.execute(select(Frame.id, Frame.result).where(Frame.id.in_(chunk))):
            people = (result or {}).get("people", [])
            positions[frame_id] = {
                p["index"]: (float(p["ground_m"][0]), float(p["ground_m"][1])) for p in people if p.get("ground_m")
            }
    places = []
    for event in events:
        placed = positions.get(event.frame_id, {})
        if event.person_i in placed and event.person_j in placed:
            places.append(ViolationPlace(event.timestamp, placed[event.person_i], placed[event.person_j]))
    return places


def violation_counts(
    session: Session,
    camera_id: str,
    *,
    since: datetime,
    until: datetime | None = None,
    bucket_s: int = MINUTE_S,
) -> list[ViolationBucket]:
    """Violation counts per time bucket (UTC-aligned, `bucket_s` wide) from `since`, empty buckets omitted.

    Buckets are integer arithmetic on epoch seconds, `epoch_s / width * width` (integer division on both
    backends), grouped in an outer query so PostgreSQL sees one grouping column rather than two textually
    different parameterised expressions. Resolution is one second: `since` and `until` are floored to whole
    seconds, `until` exclusive.
    """
    if bucket_s < 1:
        raise ValueError(f"bucket_s must be positive, got {bucket_s}")
    conditions = [ViolationEvent.camera_id == camera_id, ViolationEvent.epoch_s >= math.floor(since.timestamp())]
    if until is not None:
        conditions.append(ViolationEvent.epoch_s < math.floor(until.timestamp()))
    buckets = select(((ViolationEvent.epoch_s // bucket_s) * bucket_s).label("bucket")).where(*conditions).subquery()
    stmt = select(buckets.c.bucket, func.count()).group_by(buckets.c.bucket).order_by(buckets.c.bucket)
    return [
        ViolationBucket(start=datetime.fromtimestamp(int(bucket), UTC), count=int(count))
        for bucket, count in session.execute(stmt)
    ]
