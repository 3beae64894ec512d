"""Bodies of the camera routes (`/v1/cameras`): a camera's settings in, the camera with its evidence out."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, Field, StrictBool, model_validator
from pydantic_core import PydanticCustomError

from service.domain import feet_to_metres
from service.geometry import DEFAULT_HEIGHT_M
from service.http.schemas import Integer, Number, StrictModel

MAX_IMAGE_SIDE_PX = 100_000
# A focal length outside this many times the image's longer side is a typo, not a lens: 0.05 x is a 170-degree
# fisheye (beyond what a pinhole with OpenCV's five coefficients describes), 50 x a 2-degree telephoto.
FOCAL_RANGE_OF_IMAGE_SIDE = (0.05, 50.0)
DEFAULT_CAMERA_HEIGHT_TOLERANCE_M = 0.1

# The error type of intrinsics that do not fit the image: valid on their own, refused for this image size.
INTRINSICS_OUT_OF_IMAGE = "intrinsics_out_of_image"

FiniteNumber = Annotated[float, Field(allow_inf_nan=False, strict=True)]
PositiveFocal = Annotated[float, Field(gt=0, allow_inf_nan=False, strict=True)]


class Distortion(StrictModel):
    """Lens distortion in OpenCV's model (cv2.calibrateCamera's first coefficients) on focal-normalised
    coordinates about the principal point. Keypoints are undistorted with it before solving and measuring."""

    model: Literal["opencv"] = Field(description="`opencv`: radial k1, k2(, k3) and tangential p1, p2.")
    coefficients: list[FiniteNumber] = Field(
        min_length=4, max_length=5, description="[k1, k2, p1, p2] or [k1, k2, p1, p2, k3]."
    )


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
    known_focal_px: PositiveFocal | tuple[PositiveFocal, PositiveFocal] | None = Field(
        default=None,
        description="The focal length in pixels if known, one value or [fx, fy], each within 0.05-50 x the image's "
        "longer side (then only the ground plane and what the focal length leaves open are solved).",
    )
    principal_point_px: tuple[FiniteNumber, FiniteNumber] | None = Field(
        default=None,
        description="The principal point [cx, cy] in pixels (origin top-left), inside the image, if known. People "
        "alone cannot determine its offset across the horizon, which trades against the focal length and tilt: "
        "without it the image centre is assumed with a spread of 9 % of the image height per axis, carried into "
        "every sigma.",
    )
    distortion: Distortion | None = Field(
        default=None,
        description="The lens's OpenCV distortion if known. Without it radial distortion is estimated when the "
        "people's evidence supports it, and otherwise assumed zero with a prior carried into every sigma.",
    )
    camera_height_m: Number | None = Field(
        default=None,
        gt=0,
        le=1000,
        allow_inf_nan=False,
        description="The camera's height above the ground in metres, if the installer knows it: a constraint on the "
        "metric scale, with `camera_height_tolerance_m`.",
    )
    camera_height_tolerance_m: Number = Field(
        default=DEFAULT_CAMERA_HEIGHT_TOLERANCE_M,
        gt=0,
        le=100,
        allow_inf_nan=False,
        description="1-sigma tolerance of `camera_height_m`, metres.",
    )
    keep_images: StrictBool = Field(
        default=False,
        description="Keep posted images after their people are found, so frame overlays can be drawn. Off by "
        "default (privacy): an image is deleted once its keypoints are stored.",
    )

    @model_validator(mode="after")
    def _fits_the_image(self) -> CameraSettings:
        """Intrinsics are checked against the image they describe, so a typo is a 422, not a silent bad solve."""
        width, height = self.image_width_px, self.image_height_px
        if self.principal_point_px is not None:
            cx, cy = self.principal_point_px
            if not (0 <= cx <= width and 0 <= cy <= height):
                raise PydanticCustomError(
                    INTRINSICS_OUT_OF_IMAGE,
                    f"principal_point_px ({cx:g}, {cy:g}) lies outside the {width}x{height} image",
                )
        focal = self.known_focal_xy_px
        if focal is not None:
            low, high = (factor * max(width, height) for factor in FOCAL_RANGE_OF_IMAGE_SIDE)
            if not all(low <= f <= high for f in focal):
                raise PydanticCustomError(
                    INTRINSICS_OUT_OF_IMAGE,
                    f"known_focal_px {focal[0]:g}, {focal[1]:g} must lie within {low:g}-{high:g} px for a "
                    f"{width}x{height} image ({FOCAL_RANGE_OF_IMAGE_SIDE[0]:g}-{FOCAL_RANGE_OF_IMAGE_SIDE[1]:g} "
                    "x its longer side)",
                )
        return self

    @property
    def known_focal_xy_px(self) -> tuple[float, float] | None:
        if self.known_focal_px is None:
            return None
        if isinstance(self.known_focal_px, tuple):
            return self.known_focal_px
        return (self.known_focal_px, self.known_focal_px)


class CameraOut(BaseModel):
    """A configured camera with the evidence gathered so far."""

    id: str
    image_width_px: int
    image_height_px: int
    person_height_m: float
    equal_focal: bool
    distance_threshold_m: float
    distance_threshold_ft: float
    known_focal_px: float | tuple[float, float] | None
    principal_point_px: tuple[float, float] | None
    distortion: Distortion | None
    camera_height_m: float | None
    camera_height_tolerance_m: float
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
