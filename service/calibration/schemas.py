"""Bodies of the calibration routes, and the fields of a solve that the webhook payloads repeat.

A solve's camera (`SolvedCamera`) and how a stored version maps onto the bodies (`solution_fields`) are defined
once here: the history's entries, the camera's current calibration and the `calibration.*` webhook payloads
(service.webhooks.payloads) all say the same thing the same way.
"""

from __future__ import annotations

from datetime import datetime
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, Field

if TYPE_CHECKING:
    from service.store.models import CalibrationVersion


class CalibrationUncertainty(BaseModel):
    """1-sigma uncertainties of a solve."""

    fx_std_px: float | None
    fy_std_px: float | None
    normal_std_deg: float | None
    rho_std_m: float | None
    noise_px: float | None = Field(description="Keypoint noise estimated from the solve's residuals.")


Source = Literal["given", "estimated", "assumed"]
_SOURCE = (
    "`given`: the camera's settings gave it (exact, sigma 0); `estimated`: the people determined it (with its "
    "sigma); `assumed`: a default the people do not determine, carried with its prior's sigma into every figure."
)


class PrincipalPointOut(BaseModel):
    """Where the principal point came from, and its 1-sigma per axis."""

    source: Source = Field(description=_SOURCE)
    cx_px: float | None
    cy_px: float | None
    cx_std_px: float | None
    cy_std_px: float | None


class FocalLengthOut(BaseModel):
    """Where the focal length came from, and its 1-sigma."""

    source: Source = Field(description=_SOURCE)
    fx_px: float | None
    fy_px: float | None
    fx_std_px: float | None
    fy_std_px: float | None


class DistortionOut(BaseModel):
    """The lens the solve used: the settings' OpenCV coefficients (`given`), or a one-parameter division model
    u = u_d / (1 + k |u_d|^2) on coordinates normalised by (W + H) / 4 about the principal point, estimated when
    the people's evidence supports it and otherwise assumed 0 with its prior's sigma."""

    source: Source = Field(description=_SOURCE)
    model: Literal["opencv", "division"]
    coefficients: list[float] | None = Field(default=None, description="OpenCV [k1, k2, p1, p2, k3] when given.")
    division_k: float | None = None
    division_k_std: float | None = None


class CameraModelOut(BaseModel):
    """The camera model a solve used and found, and what it was given (see README: the camera model)."""

    principal_point: PrincipalPointOut
    focal_length: FocalLengthOut
    distortion: DistortionOut
    camera_height_m: float | None = Field(description="The camera's height above the ground (rho + ankle height).")
    ankle_height_m: float = Field(description="Height of the ankle keypoints above the ground the solve assumed.")
    noise_per_length: float | None = Field(description="Keypoint noise growing with a person's size (relative).")
    individuals: int = Field(description="Distinct people among the inliers (one walker in many frames counts once).")
    inputs: dict[str, Any] = Field(description="The camera settings the solve was given (null: not given).")


class QualityOut(BaseModel):
    """What the calibration is worth. `good`: a 2 m distance at the typical range is within 0.4 m (2 sigma);
    `rough`: within 1 m; `unreliable`: worse, or evidence too thin or narrow to trust its own sigma. An
    unreliable calibration still measures distances (with its wide sigma) but raises no violations: no events,
    no `violation.detected` webhooks."""

    grade: Literal["good", "rough", "unreliable"]
    distance_2sigma_m: float | None = Field(description="Predicted 2-sigma error of a 2 m pair at the range.")
    typical_range_m: float | None = Field(description="Median ground distance of its people from the camera.")
    reasons: list[str] = Field(description="Why the grade is not `good`.")
    advice: list[str] = Field(description="What would improve it.")
    people_needed: int = Field(description="More distinct people for a well-sampled crowd (0: enough).")


class SolvedCamera(BaseModel):
    """The camera a solve found (nulls for a solve that found none)."""

    fx_px: float | None
    fy_px: float | None
    cx_px: float | None
    cy_px: float | None
    normal: tuple[float, float, float] | None = Field(description="Unit ground normal in the camera frame, up.")
    rho_m: float | None = Field(description="Camera height above the ground plane.")
    camera_model: CameraModelOut | None = Field(
        default=None, description="Principal point, focal length and lens: given, estimated or assumed, with sigma."
    )
    quality: QualityOut | None = Field(default=None, description="What the calibration is worth (its grade).")


# The fields `solution_fields` fills, in the bodies' order.
SOLUTION_FIELDS = (*SolvedCamera.model_fields, "uncertainty", "person_height_m", "people_used", "inliers")


def solution_fields(version: CalibrationVersion) -> dict[str, Any]:
    """What a stored solve found, as the bodies carry it: the camera, its uncertainty and what it rests on."""
    normal = (version.normal_x, version.normal_y, version.normal_z)
    return {
        "fx_px": version.fx_px,
        "fy_px": version.fy_px,
        "cx_px": version.cx_px,
        "cy_px": version.cy_px,
        "normal": None if None in normal else normal,
        "rho_m": version.rho_m,
        "camera_model": CameraModelOut.model_validate(version.camera_model) if version.camera_model else None,
        "quality": QualityOut.model_validate(version.quality) if version.quality else None,
        "uncertainty": CalibrationUncertainty(
            fx_std_px=version.fx_std_px,
            fy_std_px=version.fy_std_px,
            normal_std_deg=version.normal_std_deg,
            rho_std_m=version.rho_std_m,
            noise_px=version.noise_px,
        ),
        "person_height_m": version.person_height_m,
        "people_used": version.people_used,
        "inliers": version.inliers,
    }


class _VersionHeader(BaseModel):
    version: int
    epoch: int = Field(description="The calibration epoch whose evidence the solve used.")
    status: Literal["ok", "failed"]
    reason: str | None
    is_current: bool
    forced: bool


# pydantic orders inherited fields from the last base to the first: the header's, then the camera's, then the
# class's own, which is the order clients have always received.
class CalibrationVersionOut(SolvedCamera, _VersionHeader):
    """One solve of a camera, successful or not."""

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
    `calibrated`: the fields below describe the current version; `quality.grade` says what it is worth (an
    `unreliable` one measures but raises no violations). A solve on fewer than 15 distinct people is too thin to
    report: it stays in the history as failed (`last_failure` says so), and the camera is not calibrated by it.

    Evidence and solves belong to a calibration epoch: 1 for a new camera, and one more every time the camera is
    found to have moved (`reason` camera_moved, with `moved_at`), is reset (`reset`) or changes image size
    (`image_size_changed`). Only the current epoch's people feed solves; older ones stay stored.
    """

    camera_id: str
    status: Literal["uncalibrated", "calibrating", "calibrated"]
    reason: Literal["camera_moved", "reset", "image_size_changed"] | None = Field(
        description="Why a camera that had a calibration has none now: the current epoch's reason while the "
        "epoch has no calibration yet (null otherwise, and for a new camera)."
    )
    epoch: int = Field(description="The camera's calibration epoch: 1 for a new camera, +1 at every move or reset.")
    moved_at: datetime | None = Field(
        description="When the current epoch was opened by a detected move: the timestamp of the first frame "
        "judged to be from the new view (null for other epochs)."
    )
    people_needed: int = Field(description="More usable people needed before the next solve (0 when due).")
    evidence_count: int = Field(description="Usable people stored for this camera's current epoch.")
    version: int | None
    fx_px: float | None
    fy_px: float | None
    cx_px: float | None
    cy_px: float | None
    normal: tuple[float, float, float] | None
    rho_m: float | None
    camera_model: CameraModelOut | None
    quality: QualityOut | None
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
