"""The SQL schema: cameras, their frames and per-person observations, calibration versions and violation events.

Design choices that the rest of the service relies on:

- Every table that grows with traffic carries `camera_id` and cascades from `cameras`, so deleting a camera is
  one statement and every hot query starts with an index on `camera_id`.
- Enumerations are strings with CHECK constraints, not native enums: adding a value is then a plain migration
  on both SQLite and PostgreSQL.
- Timestamps are timezone-aware UTC in Python on both backends (`UTCDateTime`); SQLite stores them as naive
  UTC text, which sorts and compares correctly because every value has the same format.
- Observations carry a coarse grid `cell` of the ankle position and a pseudo-random `sample_key`; the index
  (camera_id, usable, cell, sample_key) lets a calibration read a capped, spatially balanced sample with a few
  index range scans instead of reading every stored person (service.calibration.evidence). People are stored
  unkeyed (sample_key NULL), and the calibration job keys a camera's new people in bulk before it samples: that
  index is random in (cell, sample_key), so filling it one person per insert dirtied one page per person and was
  two thirds of the bytes written on the ingest path.
- Raw keypoints are stored as packed little-endian float32 (x, y, score) x 17, not JSON: encoding JSON floats
  was a quarter of the cost of storing a frame, and the points are only ever read back whole (`Observation.keypoints`
  unpacks them).
- An image frame's bytes live in `frame_images` only until its pose job has read them, unless the camera opted in
  to keeping images (`cameras.keep_images`); the people found are observations like any posted keypoints.
- Violation events carry `epoch_s`, whole seconds since the Unix epoch, so per-minute and per-hour counts are
  integer arithmetic that SQLite and PostgreSQL evaluate identically.
- Calibration epochs: a camera's evidence and solves belong to an epoch (`cameras.epoch`, 1 for a new camera). A
  detected move, a manual reset or a change of image size opens the next one: older people stay stored for audit
  but no longer feed solves, and the sampling index starts with (camera_id, epoch) so a solve reads its own epoch's.
- API keys store only a digest of their token (service.keys.tokens); a revoked key keeps its row, so listings
  and audits still show who had access, and when.
"""

from __future__ import annotations

import math
import struct
import uuid
from datetime import UTC, datetime
from itertools import chain
from typing import Any

import numpy as np
from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Dialect,
    Double,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    Uuid,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

# 6 ft, the social-distancing threshold the product was asked for. (The person height default is
# service.geometry.DEFAULT_HEIGHT_M; it is not imported here because importing the geometry pulls in scipy,
# which `posemetry db upgrade` and the store should not pay for.)
DEFAULT_DISTANCE_THRESHOLD_M = 1.8288
CAMERA_ID_MAX_LENGTH = 128
CLIENT_FRAME_ID_MAX_LENGTH = 128
# service.http.schemas.CLIENT_TRACK_ID_MAX_LENGTH (not imported: the store does not depend on the API).
CLIENT_TRACK_ID_MAX_LENGTH = 64
REASON_MAX_LENGTH = 200
POSTURE_MAX_LENGTH = 8
API_KEY_ID_LENGTH = 12
API_KEY_NAME_MAX_LENGTH = 100
API_KEY_DIGEST_LENGTH = 64
API_KEY_CREATED_BY_MAX_LENGTH = 120


# frames.error is TEXT; a cap keeps one bad frame from storing a novel, but leaves room for the fix to be named.
FRAME_ERROR_MAX_LENGTH = 1000


def clip_reason(message: str, limit: int = REASON_MAX_LENGTH) -> str:
    """A reason cut to fit its column, keeping the start, which says what went wrong."""
    return message if len(message) <= limit else message[: limit - 3] + "..."


def finite_or_none(value: float | None) -> float | None:
    """NaN/inf become NULL: SQLite silently stores NaN as NULL anyway, and PostgreSQL JSON rejects it."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


# sample_key is uniform in [0, SAMPLE_KEY_SPACE): 31 bits fit a signed INTEGER on every backend.
SAMPLE_KEY_SPACE = 2**31

FRAME_SOURCES = ("keypoints", "image")
# detecting: an image frame waiting for its pose job; pending: people stored, waiting to be measured.
FRAME_STATUSES = ("detecting", "pending", "done", "failed")
IMAGE_CONTENT_TYPES = ("image/jpeg", "image/png")
POSE_MODEL_MAX_LENGTH = 64
# service.observability.request_id.REQUEST_ID_MAX_LENGTH (not imported: the store does not depend on the API).
REQUEST_ID_MAX_LENGTH = 128
CONTENT_SHA256_LENGTH = 64
# COCO-17 keypoints as stored: (x px, y px, score) float32, little-endian, one row per keypoint.
KEYPOINTS_DTYPE = np.dtype("<f4")
KEYPOINT_COUNT = 17
_KEYPOINTS_STRUCT = struct.Struct(f"<{3 * KEYPOINT_COUNT}f")
CALIBRATION_STATUSES = ("ok", "failed")
QUALITY_GRADES = ("good", "rough", "unreliable")
# Why a camera's calibration epoch was opened (the first has no reason).
EPOCH_REASONS = ("camera_moved", "reset", "image_size_changed")

NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

# An auto-incrementing 64-bit key: SQLite only auto-increments a column declared exactly INTEGER PRIMARY KEY
# (which is 64-bit there anyway), PostgreSQL needs BIGINT for tables that outgrow 2^31 rows.
BigIntegerKey = BigInteger().with_variant(Integer(), "sqlite")


def utc_now() -> datetime:
    """The current time as an aware UTC datetime, the only kind the store accepts."""
    return datetime.now(UTC)


def _in(values: tuple[str, ...]) -> str:
    return "(" + ", ".join(f"'{value}'" for value in values) + ")"


class UTCDateTime(TypeDecorator[datetime]):
    """Aware UTC datetimes in and out on every backend; naive datetimes are refused, not guessed at.

    PostgreSQL stores `timestamptz`; SQLite has no time zones, so values are stored as naive UTC and the zone is
    put back on the way out. Without this, the same query returns aware datetimes on one backend and naive ones
    on the other, and comparisons between them raise.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None or value.utcoffset() is None:
            raise ValueError(f"naive datetime {value!r}: the store needs timezone-aware datetimes")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    """Declarative base with a naming convention, so constraint names are stable across backends and migrations."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map = {  # noqa: RUF012 - SQLAlchemy reads this class attribute by name
        datetime: UTCDateTime(),
        float: Double(),
        str: Text(),
        uuid.UUID: Uuid(),
    }


class Camera(Base):
    """A fixed camera as configured by its client, with the evidence counters that drive re-calibration."""

    __tablename__ = "cameras"

    id: Mapped[str] = mapped_column(String(CAMERA_ID_MAX_LENGTH), primary_key=True)
    image_width_px: Mapped[int] = mapped_column(Integer)
    image_height_px: Mapped[int] = mapped_column(Integer)
    person_height_m: Mapped[float]
    equal_focal: Mapped[bool] = mapped_column(Boolean, default=True)
    distance_threshold_m: Mapped[float] = mapped_column(default=DEFAULT_DISTANCE_THRESHOLD_M)
    known_focal_px: Mapped[float | None]
    # The camera model the installer knows (issue 16), each optional: fy when fx and fy differ (known_focal_px is
    # fx), the principal point, OpenCV lens coefficients [k1, k2, p1, p2(, k3)] and the camera's height with its
    # tolerance. service.cameras.schemas validates them; the calibration worker builds its problem from them.
    known_focal_y_px: Mapped[float | None]
    principal_point_x_px: Mapped[float | None]
    principal_point_y_px: Mapped[float | None]
    distortion_coefficients: Mapped[list[float] | None] = mapped_column(JSON)
    camera_height_m: Mapped[float | None]
    camera_height_tolerance_m: Mapped[float | None]
    # Privacy by default: an image frame's picture is dropped once its people are found, unless this is set.
    keep_images: Mapped[bool] = mapped_column(Boolean, default=False, server_default=text("false"))
    # Maintained on insert, so "is a solve due?" never has to count millions of rows.
    usable_evidence_count: Mapped[int] = mapped_column(BigInteger, default=0, server_default=text("0"))
    evidence_at_last_solve: Mapped[int] = mapped_column(BigInteger, default=0, server_default=text("0"))
    # The calibration epoch new people join, why it was opened (EPOCH_REASONS; NULL for the first) and, after a
    # detected move, the timestamp of the first frame judged to be from the new view.
    epoch: Mapped[int] = mapped_column(Integer, default=1, server_default=text("1"))
    epoch_reason: Mapped[str | None] = mapped_column(String(32))
    moved_at: Mapped[datetime | None]
    # Moves the movement test has detected over the camera's life (a counter for the metrics; resets not counted).
    moves: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(default=utc_now)

    __table_args__ = (
        CheckConstraint("image_width_px > 0 AND image_height_px > 0", name="image_size_positive"),
        CheckConstraint("person_height_m > 0", name="person_height_positive"),
        CheckConstraint("distance_threshold_m > 0", name="distance_threshold_positive"),
        CheckConstraint("known_focal_px IS NULL OR known_focal_px > 0", name="known_focal_positive"),
        CheckConstraint("known_focal_y_px IS NULL OR known_focal_y_px > 0", name="known_focal_y_positive"),
        CheckConstraint("camera_height_m IS NULL OR camera_height_m > 0", name="camera_height_positive"),
        CheckConstraint("epoch >= 1", name="epoch_positive"),
        CheckConstraint(f"epoch_reason IS NULL OR epoch_reason IN {_in(EPOCH_REASONS)}", name="epoch_reason"),
    )


class Frame(Base):
    """One posted frame: the unit of idempotency (client frame id), of work (status) and of results."""

    __tablename__ = "frames"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=uuid.uuid4)
    camera_id: Mapped[str] = mapped_column(String(CAMERA_ID_MAX_LENGTH), ForeignKey("cameras.id", ondelete="CASCADE"))
    # NULLs are distinct in the unique constraint on both backends, so frames without a client id never clash.
    client_frame_id: Mapped[str | None] = mapped_column(String(CLIENT_FRAME_ID_MAX_LENGTH))
    timestamp: Mapped[datetime]
    received_at: Mapped[datetime] = mapped_column(default=utc_now)
    source: Mapped[str] = mapped_column(String(16))
    status: Mapped[str] = mapped_column(String(16), default="pending")
    people: Mapped[int] = mapped_column(Integer, default=0)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    calibration_version: Mapped[int | None] = mapped_column(Integer)
    # Which pose model found the people of an image frame (None for posted keypoints).
    pose_model: Mapped[str | None] = mapped_column(String(POSE_MODEL_MAX_LENGTH))
    # The id of the request that posted the frame, so the jobs that handle it (pose, measuring in per-camera
    # batches) log under that id too.
    request_id: Mapped[str | None] = mapped_column(String(REQUEST_ID_MAX_LENGTH))
    # SHA-256 (hex) of what the client posted, in a canonical form (service.frames.digests.keypoint_frame_digest,
    # image_frame_digest): a post with the frame's client id and other content is a conflict, not a retry. NULL for
    # frames stored before revision 0007, whose retries cannot be told apart from conflicts.
    content_sha256: Mapped[str | None] = mapped_column(String(CONTENT_SHA256_LENGTH))
    error: Mapped[str | None]
    processed_at: Mapped[datetime | None]

    __table_args__ = (
        UniqueConstraint("camera_id", "client_frame_id"),
        # Pending work per camera (and across cameras when workers restart), oldest first.
        Index("ix_frames_status_camera_id_received_at", "status", "camera_id", "received_at"),
        # A camera's frames by capture time, newest first, a page at a time (GET .../frames): the keyset's order.
        Index("ix_frames_camera_id_timestamp_id", "camera_id", "timestamp", "id"),
        CheckConstraint(f"source IN {_in(FRAME_SOURCES)}", name="source"),
        CheckConstraint(f"status IN {_in(FRAME_STATUSES)}", name="status"),
        CheckConstraint("people >= 0", name="people_non_negative"),
    )


class Observation(Base):
    """One person in one frame: the two points calibration and measurement use, and the raw keypoints."""

    __tablename__ = "observations"

    id: Mapped[int] = mapped_column(BigIntegerKey, primary_key=True, autoincrement=True)
    camera_id: Mapped[str] = mapped_column(String(CAMERA_ID_MAX_LENGTH), ForeignKey("cameras.id", ondelete="CASCADE"))
    frame_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"))
    person_index: Mapped[int] = mapped_column(Integer)
    shoulder_x_px: Mapped[float | None]
    shoulder_y_px: Mapped[float | None]
    ankle_x_px: Mapped[float | None]
    ankle_y_px: Mapped[float | None]
    keypoints_f32: Mapped[bytes | None] = mapped_column(LargeBinary)
    # Detector output for people found in images (None for posted keypoints).
    box_left_px: Mapped[float | None]
    box_top_px: Mapped[float | None]
    box_right_px: Mapped[float | None]
    box_bottom_px: Mapped[float | None]
    detection_score: Mapped[float | None]
    # What the person looks like (service.geometry.appearance, 128 bytes), for standing people found in images:
    # calibration links one person across frames seconds apart by it. None for posted keypoints.
    appearance: Mapped[bytes | None] = mapped_column(LargeBinary)
    # The client's track id of a posted person (service.frames.schemas.PersonObservation): calibration takes one id
    # for one individual. Read by primary key with the sample only, so no index: ingest pays for the bytes alone.
    client_track_id: Mapped[str | None] = mapped_column(String(CLIENT_TRACK_ID_MAX_LENGTH))
    usable: Mapped[bool] = mapped_column(Boolean)
    unusable_reason: Mapped[str | None] = mapped_column(String(REASON_MAX_LENGTH))
    # What measuring reads of the verdict (service.domain.PersonIn): the posture (posted people: partial or None),
    # whether the ankle point is a detector box's bottom, whether the person stands at a static spot.
    posture: Mapped[str | None] = mapped_column(String(POSTURE_MAX_LENGTH))
    placed_from_box: Mapped[bool] = mapped_column(Boolean, default=False, server_default=text("false"))
    static: Mapped[bool] = mapped_column(Boolean, default=False, server_default=text("false"))
    cell: Mapped[int | None] = mapped_column(Integer)
    # The camera's calibration epoch when the person was stored (or the new one, for a frame of a detected move's
    # detection window): only the camera's current epoch feeds solves.
    epoch: Mapped[int] = mapped_column(Integer, default=1, server_default=text("1"))
    # None until the calibration job keys the person (service.calibration.evidence.key_new_evidence).
    sample_key: Mapped[int | None] = mapped_column(Integer)

    __table_args__ = (
        # Also the index behind the cascade from frames.
        UniqueConstraint("frame_id", "person_index"),
        # A camera's people: the unkeyed ones (sample_key NULL) together and in arrival order, so storing people
        # appends to one page per camera, and keying finds them in order. Deleting or resetting a camera's
        # evidence, and the cascade from cameras, use it too.
        Index("ix_observations_camera_id_sample_key_id", "camera_id", "sample_key", "id"),
        # The calibration sample: equality on (camera_id, epoch, usable, cell), then a range on sample_key.
        Index(
            "ix_observations_camera_id_epoch_usable_cell_sample_key",
            "camera_id",
            "epoch",
            "usable",
            "cell",
            "sample_key",
            sqlite_where=text("sample_key IS NOT NULL"),
            postgresql_where=text("sample_key IS NOT NULL"),
        ),
        CheckConstraint(
            "NOT usable OR (shoulder_x_px IS NOT NULL AND shoulder_y_px IS NOT NULL AND ankle_x_px IS NOT NULL "
            "AND ankle_y_px IS NOT NULL AND cell IS NOT NULL)",
            name="usable_is_complete",
        ),
        CheckConstraint("usable OR unusable_reason IS NOT NULL", name="unusable_has_reason"),
        # The cell of the ankle centre on service.geometry.evidence.SAMPLE_GRID (8 x 8), the grid both samplers use.
        # Its count is written out, not imported: importing the geometry loads scipy, which `posemetry db upgrade`
        # should not pay for (tests/calibration/test_evidence.py checks they agree). A new grid needs a migration.
        CheckConstraint("cell IS NULL OR (cell >= 0 AND cell < 64)", name="cell_on_grid"),
        CheckConstraint(f"sample_key >= 0 AND sample_key < {SAMPLE_KEY_SPACE}", name="sample_key_range"),
    )

    @property
    def keypoints(self) -> list[list[float]] | None:
        """The COCO-17 keypoints as `[[x, y, score] x 17]`, or None when the person was posted as centres."""
        return unpack_keypoints(self.keypoints_f32)

    @property
    def box_px(self) -> tuple[float, float, float, float] | None:
        """Detector box (left, top, right, bottom), or None for people that were not detected in an image."""
        box = (self.box_left_px, self.box_top_px, self.box_right_px, self.box_bottom_px)
        return None if any(v is None for v in box) else box  # type: ignore[return-value]


def pack_keypoints(keypoints: Any) -> bytes:
    """(17, 3) keypoints as the stored bytes; raises ValueError for any other shape.

    Rows of plain numbers (what the API posts) are packed by `struct`, a tenth of the cost of building a numpy
    array per person on the ingest path; arrays (from the pose models) go through numpy.
    """
    plain = not isinstance(keypoints, np.ndarray) and len(keypoints) == KEYPOINT_COUNT
    if plain and set(map(len, keypoints)) == {3}:
        try:
            return _KEYPOINTS_STRUCT.pack(*chain.from_iterable(keypoints))
        except struct.error:
            pass  # not plain numbers: numpy decides, and names the problem
        except OverflowError:
            raise ValueError("keypoints must lie within float32's range (|v| < 3.4e38)") from None
    with np.errstate(over="raise", invalid="raise"):
        try:
            array = np.asarray(keypoints, dtype=KEYPOINTS_DTYPE)
        except FloatingPointError:
            raise ValueError("keypoints must lie within float32's range (|v| < 3.4e38)") from None
    if array.shape != (KEYPOINT_COUNT, 3):
        raise ValueError(f"keypoints must be {KEYPOINT_COUNT} rows of (x, y, score), got shape {array.shape}")
    return array.tobytes()


def unpack_keypoints(data: bytes | None) -> list[list[float]] | None:
    if data is None:
        return None
    # Through float32's shortest decimal form, so a posted 0.9 reads back as 0.9, not 0.8999999761581421.
    values = [float(str(value)) for value in np.frombuffer(data, dtype=KEYPOINTS_DTYPE)]
    return [values[k : k + 3] for k in range(0, 3 * KEYPOINT_COUNT, 3)]


class FrameImage(Base):
    """The posted picture of an image frame: the pose job's input, kept afterwards only if the camera opts in."""

    __tablename__ = "frame_images"

    frame_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"), primary_key=True)
    content_type: Mapped[str] = mapped_column(String(32))
    width_px: Mapped[int] = mapped_column(Integer)
    height_px: Mapped[int] = mapped_column(Integer)
    data: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(default=utc_now)

    __table_args__ = (CheckConstraint(f"content_type IN {_in(IMAGE_CONTENT_TYPES)}", name="content_type"),)


class CalibrationVersion(Base):
    """One solve of one camera (successful or not); at most one per camera is current."""

    __tablename__ = "calibrations"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    camera_id: Mapped[str] = mapped_column(String(CAMERA_ID_MAX_LENGTH), ForeignKey("cameras.id", ondelete="CASCADE"))
    version: Mapped[int] = mapped_column(Integer)
    # The calibration epoch whose evidence the solve used.
    epoch: Mapped[int] = mapped_column(Integer, default=1, server_default=text("1"))
    status: Mapped[str] = mapped_column(String(16))
    reason: Mapped[str | None]
    fx_px: Mapped[float | None]
    fy_px: Mapped[float | None]
    cx_px: Mapped[float | None]
    cy_px: Mapped[float | None]
    normal_x: Mapped[float | None]
    normal_y: Mapped[float | None]
    normal_z: Mapped[float | None]
    rho_m: Mapped[float | None]
    fx_std_px: Mapped[float | None]
    fy_std_px: Mapped[float | None]
    normal_std_deg: Mapped[float | None]
    rho_std_m: Mapped[float | None]
    covariance: Mapped[list[list[float | None]] | None] = mapped_column(JSON)
    noise_px: Mapped[float | None]
    distortion_k: Mapped[float | None]
    # What measuring with this version needs beyond the columns above, and what the responses show about it:
    # lens, ankle height, size-dependent keypoint noise, the covariance's parameter names, where each intrinsic
    # came from with its sigma, the inputs the solve was given (service.calibration.camera_model).
    camera_model: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    # good | rough | unreliable (service.geometry.quality); an unreliable version measures but raises no alerts.
    quality_grade: Mapped[str | None] = mapped_column(String(16))
    quality: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    person_height_m: Mapped[float]
    people_used: Mapped[int] = mapped_column(Integer)
    inliers: Mapped[int] = mapped_column(Integer)
    evidence_count: Mapped[int] = mapped_column(BigInteger)
    is_current: Mapped[bool] = mapped_column(Boolean, default=False)
    forced: Mapped[bool] = mapped_column(Boolean, default=False)
    duration_s: Mapped[float | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)

    __table_args__ = (
        UniqueConstraint("camera_id", "version"),
        # The database, not only the code, guarantees a single current version per camera.
        Index(
            "uq_calibrations_camera_id_current",
            "camera_id",
            unique=True,
            sqlite_where=text("is_current"),
            postgresql_where=text("is_current"),
        ),
        CheckConstraint(f"status IN {_in(CALIBRATION_STATUSES)}", name="status"),
        CheckConstraint("NOT is_current OR status = 'ok'", name="current_is_ok"),
        CheckConstraint(
            "status <> 'ok' OR (fx_px IS NOT NULL AND fy_px IS NOT NULL AND cx_px IS NOT NULL AND cy_px IS NOT NULL "
            "AND normal_x IS NOT NULL AND normal_y IS NOT NULL AND normal_z IS NOT NULL AND rho_m IS NOT NULL)",
            name="ok_is_complete",
        ),
        CheckConstraint("version >= 1", name="version_positive"),
        CheckConstraint(f"quality_grade IS NULL OR quality_grade IN {_in(QUALITY_GRADES)}", name="quality_grade"),
    )


class MovementMonitor(Base):
    """The movement test's state for a camera (service.calibration.movement), kept between measuring jobs.

    It belongs to one epoch and one calibration version: a state of another is stale and starts again.
    """

    __tablename__ = "movement_monitors"

    camera_id: Mapped[str] = mapped_column(
        String(CAMERA_ID_MAX_LENGTH), ForeignKey("cameras.id", ondelete="CASCADE"), primary_key=True
    )
    epoch: Mapped[int] = mapped_column(Integer)
    calibration_version: Mapped[int] = mapped_column(Integer)
    state: Mapped[bytes] = mapped_column(LargeBinary)
    statistic: Mapped[float]
    updated_at: Mapped[datetime] = mapped_column(default=utc_now)


class ViolationEvent(Base):
    """A pair of people closer than their camera's threshold in one frame."""

    __tablename__ = "violation_events"

    id: Mapped[int] = mapped_column(BigIntegerKey, primary_key=True, autoincrement=True)
    camera_id: Mapped[str] = mapped_column(String(CAMERA_ID_MAX_LENGTH), ForeignKey("cameras.id", ondelete="CASCADE"))
    frame_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"))
    timestamp: Mapped[datetime]
    # floor(timestamp) in Unix seconds: time buckets are then `epoch_s / width * width` on every backend.
    epoch_s: Mapped[int] = mapped_column(BigInteger)
    person_i: Mapped[int] = mapped_column(Integer)
    person_j: Mapped[int] = mapped_column(Integer)
    distance_m: Mapped[float]
    distance_std_m: Mapped[float | None]

    __table_args__ = (
        # Recomputing a frame replaces its events instead of duplicating them; also the cascade's index.
        UniqueConstraint("frame_id", "person_i", "person_j"),
        # Bucket counts over a window: a range scan on (camera_id, epoch_s), the timestamp in integer form.
        Index("ix_violation_events_camera_id_epoch_s", "camera_id", "epoch_s"),
        CheckConstraint("person_i < person_j", name="pair_ordered"),
    )


class StaticSpot(Base):
    """Where a camera's detector keeps finding a "person" that never moves (a mannequin, a poster, a statue).

    Each image frame's boxes, and a sample of its keypoint frames' (service.frames.static), are matched to the
    camera's spots (service.cameras.static_spots); a spot seen, without moving, for `static_after_s` of frame time
    is static: the people found there give no evidence and raise no violation. A spot unseen for a while is
    forgotten, so a person who stood still and left leaves nothing behind.
    """

    __tablename__ = "static_spots"

    id: Mapped[int] = mapped_column(BigIntegerKey, primary_key=True, autoincrement=True)
    camera_id: Mapped[str] = mapped_column(String(CAMERA_ID_MAX_LENGTH), ForeignKey("cameras.id", ondelete="CASCADE"))
    left_px: Mapped[float]
    top_px: Mapped[float]
    right_px: Mapped[float]
    bottom_px: Mapped[float]
    first_seen: Mapped[datetime]
    last_seen: Mapped[datetime]
    sightings: Mapped[int] = mapped_column(Integer)

    __table_args__ = (Index("ix_static_spots_camera_id", "camera_id"),)


class ApiKey(Base):
    """An API key: its token's digest (never the token), what it may do, and its life cycle."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(API_KEY_ID_LENGTH), primary_key=True)
    name: Mapped[str] = mapped_column(String(API_KEY_NAME_MAX_LENGTH))
    token_digest: Mapped[str] = mapped_column(String(API_KEY_DIGEST_LENGTH))
    admin: Mapped[bool] = mapped_column(Boolean, default=False)
    # The camera ids the key is limited to (a JSON list); NULL: every camera. Admin keys are never limited.
    cameras: Mapped[list[str] | None] = mapped_column(JSON(none_as_null=True))
    # Who issued it: another key's id, `POSEMETRY_ADMIN_KEY`, `posemetry keys` or `posemetry serve`.
    created_by: Mapped[str] = mapped_column(String(API_KEY_CREATED_BY_MAX_LENGTH))
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    # Written at most about once a minute per key and API process (service.keys.authenticator), not on every request.
    last_used_at: Mapped[datetime | None]
    expires_at: Mapped[datetime | None]
    revoked_at: Mapped[datetime | None]

    __table_args__ = (CheckConstraint("NOT admin OR cameras IS NULL", name="admin_unscoped"),)
