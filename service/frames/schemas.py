"""Bodies of the frame routes: a posted frame's people, the answer to a post, and a stored frame with its result."""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic_core import PydanticCustomError

from service.cameras.schemas import MAX_IMAGE_SIDE_PX
from service.domain import Posture
from service.http.schemas import CLIENT_FRAME_ID_PATTERN, CLIENT_TRACK_ID_PATTERN, Score, StrictModel, Timestamp

COCO_KEYPOINTS = 17
# Every pixel coordinate, whatever its score: finite and within ten times the largest image side of the origin. The
# frames service then holds it to the camera's image (service.frames.service.people_for_camera); this bound alone
# keeps every number storable (keypoints are packed as float32, whose range ends at 3.4e38: 1e39 with a score of 0
# once failed a whole write batch) and is in the published schema, so a client learns it from the contract.
COORDINATE_LIMIT_PX = 10 * MAX_IMAGE_SIDE_PX
CoordinatePx = Annotated[
    float, Field(ge=-COORDINATE_LIMIT_PX, le=COORDINATE_LIMIT_PX, allow_inf_nan=False, strict=True)
]
PointPx = tuple[CoordinatePx, CoordinatePx]
Keypoint = tuple[CoordinatePx, CoordinatePx, Score]


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
    track_id: str | None = Field(
        default=None,
        pattern=CLIENT_TRACK_ID_PATTERN,
        description="The client's id for this person across this camera's frames, e.g. from its tracker; sightings "
        "with one track_id less than a minute apart are one individual for calibration (after a longer gap without "
        "it, another one). Never give one id to two people at once; a tracker whose numbering restarts should "
        "prefix its ids with its start time (a reuse within a minute would merge two people). Unique within a "
        "frame. It comes back with the person in results, `/distances` answers and violation alerts.",
        examples=["17", "2026-01-01T12:00:00Z:17"],
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

    @model_validator(mode="after")
    def _one_person_per_track(self) -> KeypointFrame:
        """Two people of one frame are never one individual: a repeated id is the client's mistake, and linking
        on it would merge two people's heights."""
        seen: dict[str, int] = {}
        for index, person in enumerate(self.people):
            if person.track_id is not None:
                first = seen.setdefault(person.track_id, index)
                if first != index:
                    raise PydanticCustomError(
                        "duplicate_track_id",
                        "people {first} and {index} have the same track_id: one person per track in a frame",
                        {"first": first, "index": index},
                    )
        return self


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
    placed_from: Literal["ankles", "box", "shoulders"] | None = Field(
        description="What put the person on the ground: `ankles` (their ankle centre), `box` (the pose was not "
        "read, the bottom of their detector box, clear of the frame edge and of other people's boxes, with a wider "
        "sigma) or `shoulders` (lower body hidden: the shoulder centre at the height prior, or a seated height). "
        "Null when the person could not be placed."
    )
    ground_m: tuple[float, float] | None
    point_m: tuple[float, float, float] | None
    static: bool = Field(
        default=False,
        description="Found at one of the camera's static spots (nothing there has moved for `static_after_s`: a "
        "mannequin, a poster): measured, but in no violation and no calibration evidence.",
    )
    track_id: str | None = Field(
        default=None,
        description="The person's `track_id` as posted (the client's tracker id), so that results, pairs and "
        "alerts can be joined to the client's own people; null when none was posted (always for image frames).",
    )


class PairDistance(BaseModel):
    """Distance between two people of a frame (indices into `people`, i < j), with its 1-sigma uncertainty."""

    i: int
    j: int
    distance_m: float | None
    distance_std_m: float | None


class FrameResult(BaseModel):
    """Positions, every pair's distance and the pairs closer than the camera's threshold.

    A calibration graded `unreliable` still measures every pair (with its wide `distance_std_m`), but its
    verdicts are not trusted: `violations` is empty, no violation event is stored and no webhook raised, and
    `alerts_suppressed` says why.
    """

    calibration_version: int
    distance_threshold_m: float
    people: list[PersonPosition]
    pairs: list[PairDistance]
    violations: list[PairDistance]
    calibration_grade: Literal["good", "rough", "unreliable"] | None = Field(
        default=None, description="The calibration's quality grade (null for versions stored before grades)."
    )
    alerts_suppressed: str | None = Field(
        default=None, description="Why pairs under the threshold raised no violations (an unreliable calibration)."
    )


class DetectedPersonOut(BaseModel):
    """A person the pose model found in an image frame (index as in the result's `people`)."""

    index: int
    box_px: tuple[float, float, float, float] | None = Field(description="Detector box: left, top, right, bottom.")
    detection_score: float | None
    keypoints: list[tuple[float, float, float]] | None = Field(description="COCO-17 [x_px, y_px, score].")
    shoulder_px: tuple[float, float] | None
    ankle_px: tuple[float, float] | None
    posture: Posture | None = Field(
        description="The pose's verdict: `standing` (calibration evidence), `seated` (legs seen but folded: placed "
        "at a seated height), `partial` (lower body not seen: placed from the shoulders) or `unknown` (shoulders not "
        "seen: placed from the detector box's bottom where it is a ground contact, else not at all). Null for "
        "people stored before the service kept it, unless their reason said."
    )
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


class FrameSummary(BaseModel):
    """A frame in a list: its state and counts, without the people and pairs (`url` has those)."""

    frame_id: uuid.UUID
    camera_id: str
    client_frame_id: str | None
    source: Literal["keypoints", "image"]
    timestamp: datetime
    received_at: datetime
    status: FrameStatus
    people: int
    violations: int | None = Field(description="Pairs closer than the threshold, once measured (null before).")
    calibration_version: int | None
    processed_at: datetime | None
    error: str | None
    image_kept: bool
    url: str
    links: dict[str, str] = Field(description="Related resources: overlay and top-down pictures.")


class FrameList(BaseModel):
    """One page of a camera's frames, newest first (by `timestamp`, then id); pass `next_before` as `before` for
    the next page (null: last page)."""

    items: list[FrameSummary]
    next_before: str | None
