"""Bodies of the camera routes (`/v1/cameras`): a camera's settings in, the camera with its evidence out."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, Field, StrictBool

from service.domain import feet_to_metres
from service.geometry import DEFAULT_HEIGHT_M
from service.http.schemas import Integer, Number, StrictModel

MAX_IMAGE_SIDE_PX = 100_000


class DistanceThreshold(StrictModel):
    """A distance with its unit, because social-distancing rules are written in feet in some places, metres in
    others; the service stores and reports metres."""

    # At least a centimetre (or a hundredth of a foot): a positive but tiny value such as 5e-324 ft would round
    # to 0 m on conversion, which the store rightly refuses.
    value: Number = Field(ge=0.01, le=1000, allow_inf_nan=False, description="The threshold in `unit`.")
    unit: Literal["m", "ft"] = Field(description="`m` (metres) or `ft` (international feet, 0.3048 m).")

    @property
    def metres(self) -> float:
        return feet_to_metres(self.value) if self.unit == "ft" else self.value


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


class StaticSpotOut(BaseModel):
    """A place where the detector keeps finding a "person" that never moves (a mannequin, a poster, a statue)."""

    box_px: tuple[float, float, float, float] = Field(description="left, top, right, bottom of its first box.")
    first_seen: datetime = Field(description="Frame time of its first sighting.")
    last_seen: datetime = Field(description="Frame time of its latest sighting.")
    sightings: int = Field(description="Frames it was found in, unmoved.")


class StaticSpotList(BaseModel):
    """The camera's static spots: people found there give no calibration evidence and raise no violation."""

    static_after_s: float = Field(description="How long a spot must stay unmoved to be static (a setting).")
    items: list[StaticSpotOut]
