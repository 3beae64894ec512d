"""Request and response bodies of the v1 HTTP API (pydantic v2): the wire contract of issue 3.

Requests are strict because everything a client posts ends up as calibration evidence: unknown fields are
refused (a typo such as `anklee` would otherwise silently drop a person's ankle), numbers must be finite (Python's
JSON parser accepts `NaN` and `Infinity`, and `1e999` overflows to infinity), scores lie in [0, 1], and a COCO-17
person has exactly 17 keypoints. Checks that need the camera (coordinates within a margin of its image) or the
settings (people per frame) happen in the routers, which report them in the same error format.

Names carry units (`_px`, `_m`, `_deg`, `_s`) so that a client never has to guess one.
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    AwareDatetime,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictBool,
    WithJsonSchema,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from service.geometry import DEFAULT_HEIGHT_M

CAMERA_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
CLIENT_FRAME_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,127}$"
COCO_KEYPOINTS = 17
METRES_PER_FOOT = 0.3048
MAX_IMAGE_SIDE_PX = 100_000


def _not_a_boolean(value: object) -> object:
    if isinstance(value, bool):
        raise PydanticCustomError("bool_not_number", "Input should be a number, not true or false")
    return value


# JSON true/false and strings are not numbers, but pydantic's lax mode reads them as numbers (a width of `true`
# pixels, a score of "0.5"). Strict floats refuse both (in Rust: keypoints hold a thousand per frame); strict
# integers would also refuse 640.0, which JSON Schema calls an integer, so integers only refuse booleans.
Number = Annotated[float, Field(strict=True)]
Integer = Annotated[int, BeforeValidator(_not_a_boolean)]
# Every pixel coordinate, whatever its score: finite and within ten times the largest image side of the origin. The
# routers then hold it to the camera's image (service.routers.common); this bound alone keeps every number storable
# (keypoints are packed as float32, whose range ends at 3.4e38: 1e39 with a score of 0 once failed a whole write
# batch) and is in the published schema, so a client learns it from the contract.
COORDINATE_LIMIT_PX = 10 * MAX_IMAGE_SIDE_PX
CoordinatePx = Annotated[
    float, Field(ge=-COORDINATE_LIMIT_PX, le=COORDINATE_LIMIT_PX, allow_inf_nan=False, strict=True)
]
Score = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False, strict=True)]
PointPx = tuple[CoordinatePx, CoordinatePx]
Keypoint = tuple[CoordinatePx, CoordinatePx, Score]
CameraId = Annotated[str, Field(pattern=CAMERA_ID_PATTERN, examples=["lobby-1"])]
# Timestamps are RFC 3339 with a zone, or Unix seconds: a JSON number (pydantic reads magnitudes above 2e10 as
# milliseconds, as JavaScript clients send them) or, in a query string or form, its digits. The JSON schema says
# exactly that, so that what the contract calls valid is what the API accepts. Every instant must exist in UTC
# (years 1-9999): "0001-01-01T00:00:00+01:00" is a valid RFC 3339 text for a moment before year 1, and converting
# it made the store, the violation window and key expiry fail with an OverflowError (a 500) before this check.
UNIX_SECONDS_TEXT_PATTERN = r"^-?[0-9]{1,13}(\.[0-9]+)?$"
_UNIX_MS_MIN, _UNIX_MS_END = -62_135_596_800_000, 253_402_300_800_000  # 0001-01-01 and 10000-01-01, in ms
TIMESTAMP_JSON_SCHEMA = {
    "anyOf": [
        {"type": "string", "format": "date-time"},
        {"type": "number", "minimum": _UNIX_MS_MIN, "exclusiveMaximum": _UNIX_MS_END},
        {"type": "string", "pattern": UNIX_SECONDS_TEXT_PATTERN},
    ]
}


def _exists_in_utc(value: datetime) -> datetime:
    try:
        value.astimezone(UTC)
    except OverflowError:
        raise PydanticCustomError(
            "timestamp_out_of_range",
            "{timestamp} is outside the years 1-9999 once converted to UTC",
            {"timestamp": value.isoformat()},
        ) from None
    return value


Timestamp = Annotated[AwareDatetime, AfterValidator(_exists_in_utc), WithJsonSchema(TIMESTAMP_JSON_SCHEMA)]
# In a query string or a form everything is text.
TIMESTAMP_TEXT_JSON_SCHEMA = {"anyOf": [TIMESTAMP_JSON_SCHEMA["anyOf"][0], TIMESTAMP_JSON_SCHEMA["anyOf"][2]]}
TimestampText = Annotated[AwareDatetime, AfterValidator(_exists_in_utc), WithJsonSchema(TIMESTAMP_TEXT_JSON_SCHEMA)]


class StrictModel(BaseModel):
    """Base of every request body: unknown fields are an error, not silently ignored."""

    model_config = ConfigDict(extra="forbid")


# --------------------------------------------------------------------------------------------------- cameras


class DistanceThreshold(StrictModel):
    """A distance with its unit, because social-distancing rules are written in feet in some places, metres in
    others; the service stores and reports metres."""

    # At least a centimetre (or a hundredth of a foot): a positive but tiny value such as 5e-324 ft would round
    # to 0 m on conversion, which the store rightly refuses.
    value: Number = Field(ge=0.01, le=1000, allow_inf_nan=False, description="The threshold in `unit`.")
    unit: Literal["m", "ft"] = Field(description="`m` (metres) or `ft` (international feet, 0.3048 m).")

    @property
    def metres(self) -> float:
        return self.value * METRES_PER_FOOT if self.unit == "ft" else self.value


DEFAULT_DISTANCE_THRESHOLD = DistanceThreshold(value=6, unit="ft")


class CameraSettings(StrictModel):
    """What a client tells the service about one fixed camera (`PUT /v1/cameras/{camera_id}`)."""

    image_width_px: Integer = Field(gt=0, le=MAX_IMAGE_SIDE_PX, description="Width of the camera's images in pixels.")
    image_height_px: Integer = Field(gt=0, le=MAX_IMAGE_SIDE_PX, description="Height of the camera's images in pixels.")
    person_height_m: Number = Field(
        default=DEFAULT_HEIGHT_M,
        ge=0.3,
        le=2.5,
        allow_inf_nan=False,
        description="Mean height from ankle centre to shoulder centre of the people this camera sees, in metres. "
        f"The default {DEFAULT_HEIGHT_M} m is an adult average (about 0.78 of stature); it sets the metric scale.",
    )
    equal_focal: StrictBool = Field(
        default=True, description="Assume square pixels (fx = fy); true for almost every modern camera."
    )
    distance_threshold: DistanceThreshold = Field(
        default=DEFAULT_DISTANCE_THRESHOLD,
        description="Pairs of people closer than this are violations. Default 6 ft (1.8288 m).",
    )
    known_focal_px: Number | None = Field(
        default=None,
        gt=0,
        le=1e6,
        allow_inf_nan=False,
        description="The focal length in pixels if known (then only the ground plane is solved).",
    )
    keep_images: StrictBool = Field(
        default=False,
        description="Keep posted images after their people are found, so frame overlays can be drawn. Off by "
        "default (privacy): an image is deleted once its keypoints are stored.",
    )


class CameraOut(BaseModel):
    """A configured camera with the evidence gathered so far."""

    id: str
    image_width_px: int
    image_height_px: int
    person_height_m: float
    equal_focal: bool
    distance_threshold_m: float
    distance_threshold_ft: float
    known_focal_px: float | None
    keep_images: bool
    usable_evidence_count: int = Field(description="Stored people usable as calibration evidence.")
    created_at: datetime
    updated_at: datetime
    url: str


class CameraList(BaseModel):
    """One page of cameras in id order; pass `next_after` as `after` for the next page (null: last page)."""

    items: list[CameraOut]
    next_after: str | None


# --------------------------------------------------------------------------------------------------- frames


# The two forms of a person in the JSON schema, so that what the schema calls valid is what the validators accept:
# `keypoints` (and no centres), or a `shoulder` centre with an optional `ankle` (and no keypoints).
_ONE_FORM_JSON_SCHEMA = {
    "anyOf": [
        {
            "required": ["keypoints"],
            "properties": {"keypoints": {"type": "array"}, "shoulder": {"type": "null"}, "ankle": {"type": "null"}},
        },
        {"required": ["shoulder"], "properties": {"keypoints": {"type": "null"}, "shoulder": {"type": "array"}}},
    ]
}


class PersonObservation(StrictModel):
    """One person: either COCO-17 `keypoints` (what pose models emit) or explicit `shoulder`/`ankle` centres."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_ONE_FORM_JSON_SCHEMA)

    keypoints: list[Keypoint] | None = Field(
        default=None,
        description="COCO-17 keypoints in COCO order, each [x_px, y_px, score] with score in [0, 1].",
        # Documented only: the validator below checks the count with a message that says what COCO-17 means.
        json_schema_extra={"minItems": COCO_KEYPOINTS, "maxItems": COCO_KEYPOINTS},
    )
    shoulder: PointPx | None = Field(default=None, description="Shoulder centre [x_px, y_px] (centres form).")
    ankle: PointPx | None = Field(
        default=None, description="Ankle centre [x_px, y_px] (centres form); null or absent when not visible."
    )

    @field_validator("keypoints")
    @classmethod
    def _seventeen(cls, value: list[Keypoint] | None) -> list[Keypoint] | None:
        """Say what COCO-17 means rather than pydantic's generic list-length message.

        An after-validator: a before-validator would make pydantic build Python objects from the JSON first,
        which doubled the cost of parsing a frame.
        """
        if value is not None and len(value) != COCO_KEYPOINTS:
            raise ValueError(f"COCO-17 needs exactly {COCO_KEYPOINTS} keypoints [x, y, score], got {len(value)}")
        return value

    @model_validator(mode="after")
    def _one_form(self) -> PersonObservation:
        """A person is described one way only, so there is never a question of which points win."""
        if self.keypoints is not None:
            if self.shoulder is not None or self.ankle is not None:
                raise ValueError("give either `keypoints` or `shoulder`/`ankle` centres, not both")
        elif self.shoulder is None:
            raise ValueError("a person needs `keypoints` (COCO-17) or at least a `shoulder` centre")
        return self


class KeypointFrame(StrictModel):
    """One frame of one camera (`POST /v1/cameras/{camera_id}/keypoints`)."""

    timestamp: Timestamp = Field(
        description="When the frame was captured: RFC 3339 with a time zone, or Unix seconds.",
        examples=["2026-01-01T12:00:00Z"],
    )
    frame_id: str | None = Field(
        default=None,
        pattern=CLIENT_FRAME_ID_PATTERN,
        description="The client's id for this frame: posting the same id again is a retry of the same frame.",
    )
    people: list[PersonObservation] = Field(description="The people detected in the frame (may be empty).")


class DistanceRequest(StrictModel):
    """People to measure with the camera's current calibration (`POST /v1/cameras/{camera_id}/distances`)."""

    people: list[PersonObservation]


FrameStatus = Literal["detecting", "pending", "done", "failed"]


class FrameAccepted(BaseModel):
    """The answer to a posted frame: where its result will appear."""

    frame_id: uuid.UUID
    client_frame_id: str | None
    status: FrameStatus
    people: int
    created: bool = Field(description="False when this was a retry of a frame already stored.")
    url: str


class PersonPosition(BaseModel):
    """Where one person stands.

    `ground_m` is [right, forward] on the ground plane from the point straight below the camera: `forward`
    along the camera's viewing direction projected onto the ground, `right` to its right. `point_m` is the
    same point in the camera frame (x right, y down, z forward). Null when the person could not be placed.
    """

    index: int
    placed_from: Literal["ankles", "shoulders"] | None
    ground_m: tuple[float, float] | None
    point_m: tuple[float, float, float] | None


class PairDistance(BaseModel):
    """Distance between two people of a frame (indices into `people`, i < j), with its 1-sigma uncertainty."""

    i: int
    j: int
    distance_m: float | None
    distance_std_m: float | None


class FrameResult(BaseModel):
    """Positions, every pair's distance and the pairs closer than the camera's threshold."""

    calibration_version: int
    distance_threshold_m: float
    people: list[PersonPosition]
    pairs: list[PairDistance]
    violations: list[PairDistance]


class DetectedPersonOut(BaseModel):
    """A person the pose model found in an image frame (index as in the result's `people`)."""

    index: int
    box_px: tuple[float, float, float, float] | None = Field(description="Detector box: left, top, right, bottom.")
    detection_score: float | None
    keypoints: list[tuple[float, float, float]] | None = Field(description="COCO-17 [x_px, y_px, score].")
    shoulder_px: tuple[float, float] | None
    ankle_px: tuple[float, float] | None
    usable: bool = Field(description="Whether this person counts as calibration evidence.")
    unusable_reason: str | None


class FrameOut(BaseModel):
    """A stored frame: `detecting` (an image waiting for pose), then `pending` until a calibration exists and a
    worker has measured it, then `done` (or `failed`, with `error`)."""

    frame_id: uuid.UUID
    camera_id: str
    client_frame_id: str | None
    source: Literal["keypoints", "image"]
    timestamp: datetime
    received_at: datetime
    status: FrameStatus
    people: int
    pose_model: str | None = Field(description="The pose model that found the people of an image frame.")
    detections: list[DetectedPersonOut] | None = Field(
        default=None, description="Image frames: what the pose model found, once it has run."
    )
    image_kept: bool = Field(description="Whether the image is stored (the camera's keep_images).")
    links: dict[str, str] = Field(description="Related resources: overlay and top-down pictures.")
    calibration_version: int | None
    processed_at: datetime | None
    error: str | None
    result: FrameResult | None


# --------------------------------------------------------------------------------------------------- calibration


class CalibrationUncertainty(BaseModel):
    """1-sigma uncertainties of a solve."""

    fx_std_px: float | None
    fy_std_px: float | None
    normal_std_deg: float | None
    rho_std_m: float | None
    noise_px: float | None = Field(description="Keypoint noise estimated from the solve's residuals.")


class CalibrationVersionOut(BaseModel):
    """One solve of a camera, successful or not."""

    version: int
    status: Literal["ok", "failed"]
    reason: str | None
    is_current: bool
    forced: bool
    fx_px: float | None
    fy_px: float | None
    cx_px: float | None
    cy_px: float | None
    normal: tuple[float, float, float] | None = Field(description="Unit ground normal in the camera frame, up.")
    rho_m: float | None = Field(description="Camera height above the ground plane.")
    uncertainty: CalibrationUncertainty
    person_height_m: float
    people_used: int
    inliers: int
    evidence_count: int = Field(description="Usable people stored when this solve ran.")
    duration_s: float | None
    created_at: datetime


class CalibrationStatus(BaseModel):
    """A camera's calibration state (`GET /v1/cameras/{camera_id}/calibration`).

    `uncalibrated`: no usable calibration yet and none due; `people_needed` says how many more usable people
    (both shoulders and both ankles seen, not at the image border) must arrive before the next solve.
    `calibrating`: enough evidence for a solve that has not produced a current calibration yet.
    `calibrated`: the fields below describe the current version.
    """

    camera_id: str
    status: Literal["uncalibrated", "calibrating", "calibrated"]
    people_needed: int = Field(description="More usable people needed before the next solve (0 when due).")
    evidence_count: int = Field(description="Usable people stored for this camera now.")
    version: int | None
    fx_px: float | None
    fy_px: float | None
    cx_px: float | None
    cy_px: float | None
    normal: tuple[float, float, float] | None
    rho_m: float | None
    uncertainty: CalibrationUncertainty | None
    person_height_m: float | None
    people_used: int | None
    inliers: int | None
    solved_evidence_count: int | None = Field(description="Usable people stored when the current version ran.")
    last_failure: str | None = Field(description="Why the latest solve failed, when it did.")
    updated_at: datetime | None


class CalibrationHistory(BaseModel):
    """Versions newest first; pass `next_before` as `before` for the next page (null: last page)."""

    items: list[CalibrationVersionOut]
    next_before: int | None


class CalibrationRequested(BaseModel):
    """The answer to a forced re-solve: it runs in a worker; poll the calibration for its outcome."""

    camera_id: str
    forced: bool
    url: str


# --------------------------------------------------------------------------------------------------- violations


class ViolationBucketOut(BaseModel):
    start: datetime
    count: int


class ViolationCounts(BaseModel):
    """Violations per UTC-aligned time bucket in [since, until); empty buckets are omitted."""

    camera_id: str
    since: datetime
    until: datetime
    bucket: Literal["minute", "hour"]
    bucket_s: int
    total: int
    buckets: list[ViolationBucketOut]


# --------------------------------------------------------------------------------------------------- health


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    status: Literal["ready"]
    checks: dict[str, str]
