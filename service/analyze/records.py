"""The shapes of what `posemetry analyze` writes: calibration.json and one JSON line per frame (pydantic models).

Names follow the API (units in names, `_px`, `_m`, `_deg`; `ground_m` as in a frame's result), so a user who
knows one knows the other. Pixels have their origin top-left; the camera frame is x right, y down, z forward; the
ground plane is N . X + rho = 0 with N pointing up and rho the camera's height above the ground in metres.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from service.domain import Posture

CONVENTIONS = (
    "pixels: origin top-left, x right, y down; camera frame: x right, y down, z forward (metres); ground plane: "
    "normal . X + rho_m = 0 with the unit normal pointing up, rho_m = camera height above the ground; ground_m: "
    "[right, forward] metres on the ground from the point below the camera, forward = the viewing direction "
    "projected onto the ground"
)
CalibrationRole = Literal["inlier", "outlier", "unused"]


class CalibrationUncertaintyRecord(BaseModel):
    """1-sigma uncertainties (Gauss-Newton covariance at the solution)."""

    fx_std_px: float
    fy_std_px: float
    normal_std_deg: float
    rho_std_m: float
    cx_std_px: float = 0.0
    cy_std_px: float = 0.0
    noise_px: float = Field(description="Keypoint noise estimated from the solve's residuals.")
    noise_per_length: float = Field(default=0.0, description="Keypoint noise growing with a person's size.")
    covariance: list[list[float]] = Field(description="Over `covariance_parameters`.")
    covariance_parameters: list[str]


class EvidenceRecord(BaseModel):
    """What the calibration rests on."""

    frames: int = Field(description="Frames analysed (pose run on them).")
    frames_skipped: int = Field(description="Frames the source could not deliver (unreadable, other size).")
    people_seen: int
    usable: int = Field(description="People usable as calibration evidence (upright, shoulders and ankles seen).")
    unusable_reasons: dict[str, int]
    used: int = Field(description="Usable people solved on: repeats (still people) collapsed, then capped.")
    inliers: int = Field(description="People the solved camera explains.")


class SourceRecord(BaseModel):
    path: str
    kind: Literal["video", "images"]
    fps: float | None
    stride: int


class QualityRecord(BaseModel):
    """What the calibration is worth (service.geometry.quality)."""

    grade: Literal["good", "rough", "unreliable"]
    distance_2sigma_m: float | None = Field(description="Predicted 2-sigma error of a 2 m distance at the range.")
    typical_range_m: float | None
    reasons: list[str]
    advice: list[str]
    people_needed: int


class CalibrationRecord(BaseModel):
    """calibration.json: the camera solved once from every analysed frame, or why it could not be."""

    status: Literal["ok", "failed"]
    reason: str | None = None
    fx_px: float | None = None
    fy_px: float | None = None
    cx_px: float | None = None
    cy_px: float | None = None
    normal: tuple[float, float, float] | None = Field(
        default=None, description="Unit ground normal in the camera frame, pointing up."
    )
    rho_m: float | None = Field(default=None, description="Camera height above the ground plane.")
    tilt_deg: float | None = Field(default=None, description="How far the optical axis points below the horizon.")
    roll_deg: float | None = Field(default=None, description="Rotation of the image about the optical axis.")
    distortion_k: float | None = Field(
        default=None, description="Division-model coefficient on frame-normalised coordinates (0: none)."
    )
    lens_coefficients: tuple[float, float, float, float, float] | None = Field(
        default=None, description="The given OpenCV lens (k1, k2, p1, p2, k3), when one was given."
    )
    camera_height_m: float | None = Field(default=None, description="Camera height above the ground (rho + ankle).")
    principal_point_source: str | None = Field(default=None, description="given, estimated or assumed.")
    focal_source: str | None = Field(default=None, description="given or estimated.")
    distortion_source: str | None = Field(default=None, description="given, estimated or assumed.")
    individuals: int | None = Field(default=None, description="Distinct people among the inliers.")
    quality: QualityRecord | None = None
    uncertainty: CalibrationUncertaintyRecord | None = None
    reprojection_rms_px: float | None = None
    evidence: EvidenceRecord
    image_size_px: tuple[int, int]
    person_height_m: float
    pose_model: str
    source: SourceRecord
    options: dict[str, Any]
    conventions: str = CONVENTIONS
    duration_s: float = Field(description="Time the solve took.")
    posemetry_version: str
    warnings: list[str] = Field(
        default_factory=list, description="What the run could not do with its input, and what that costs."
    )


class PersonRecord(BaseModel):
    """One person in one frame."""

    index: int
    box_px: tuple[float, float, float, float] | None = Field(description="Detector box: left, top, right, bottom.")
    detection_score: float | None
    keypoints: list[tuple[float, float, float]] | None = Field(description="COCO-17 [x_px, y_px, score].")
    shoulder_px: tuple[float, float] | None = Field(description="Shoulder centre (null when not confidently seen).")
    ankle_px: tuple[float, float] | None = Field(description="Ankle centre (null when not confidently seen).")
    posture: Posture | None = Field(
        description="The pose's verdict: `standing` (calibration evidence), `seated` (legs seen but folded), `partial` "
        "(lower body not seen) or `unknown` (shoulders not seen)."
    )
    usable: bool = Field(description="Whether this person is calibration evidence.")
    unusable_reason: str | None
    calibration: CalibrationRole | None = Field(
        description="For usable people: `inlier` (the solved camera explains them), `outlier` (rejected by the "
        "solve), `unused` (a repeat of someone standing still, or left out of a capped sample)."
    )
    placed_from: Literal["ankles", "box", "shoulders"] | None = Field(
        description="`ankles`, `box` (the detector box's bottom: the pose was not read) or `shoulders`."
    )
    ground_m: tuple[float, float] | None
    point_m: tuple[float, float, float] | None = Field(description="The ground point in the camera frame.")
    nearest_index: int | None = Field(description="The nearest placed person in this frame.")
    nearest_m: float | None
    in_violation: bool = Field(description="In at least one pair closer than the threshold.")


class PairRecord(BaseModel):
    """Two people of a frame (indices, i < j)."""

    i: int
    j: int
    distance_m: float | None
    distance_std_m: float | None = Field(description="1-sigma uncertainty of distance_m.")
    violation: bool


class FrameRecord(BaseModel):
    """One line of frames.jsonl."""

    frame: int = Field(description="Frame number in the source (video frame, or image position in name order).")
    time_s: float | None
    file: str | None
    people: list[PersonRecord]
    pairs: list[PairRecord]
    violations: int
