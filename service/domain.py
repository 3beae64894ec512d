"""The plain values the rooms hand each other: a person of a posted frame, a measured frame, a solve's outcome.

Standard library only, so that the pure parts (keypoints, measuring, the pictures, `posemetry analyze`) can build
and read them without importing SQLAlchemy, pydantic or the geometry. The store turns them into rows; the API and
the jobs build them.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any, Final, Literal, Protocol

if TYPE_CHECKING:
    from service.geometry import Calibration

Point = tuple[float, float]
Posture = Literal["standing", "seated", "partial", "unknown"]
"""The pose pipeline's verdict on a person found in an image (service.pose.assess): `standing` (calibration
evidence), `seated` (legs seen but folded), `partial` (lower body not seen) or `unknown` (shoulders not seen)."""
POSTURES: Final[tuple[Posture, ...]] = ("standing", "seated", "partial", "unknown")
METRES_PER_FOOT = 0.3048  # the international foot: thresholds and labels may be given in feet
# Lengths converted between feet and metres are rounded to this many decimals (nanometres, or nano-feet): in binary
# floating point 6 ft would otherwise be 1.8288000000000002 m, and that is what clients would read back.
CONVERTED_DECIMALS = 9


def feet_to_metres(feet: float) -> float:
    return round(feet * METRES_PER_FOOT, CONVERTED_DECIMALS)


def metres_to_feet(metres: float) -> float:
    return round(metres / METRES_PER_FOOT, CONVERTED_DECIMALS)


# What a job did, as the jobs return it (RQ keeps it in its logs; tests assert on it).
DONE = "done"
PENDING = "pending"
FAILED = "failed"
GONE = "gone"
SKIPPED = "skipped"


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
    appearance: bytes | None = None
    """What the person looks like (service.geometry.appearance), for linking them across frames seconds apart;
    only from the image pipeline (posted keypoints carry none)."""
    track_id: str | None = None
    """The client's id for this person across the camera's frames (from its tracker): one id, one individual for
    calibration. Only posted keypoint frames carry one."""
    posture: Posture | None = None
    """The pose pipeline's verdict, for people found in images; for posted people `partial` when their shoulders
    came without their ankles, else None (the client's pose model gave no posture). Measuring places a `seated` or
    `partial` person from their shoulders at their own height prior."""
    placed_from_box: bool = False
    """`ankle_px` is the bottom of the detector box, not the ankles (service.frames.keypoints.place_from_boxes):
    measured with the wider sigma of that cue, never evidence."""
    static: bool = False
    """Found at one of the camera's static spots (a mannequin): measured, in no violation, never evidence."""


@dataclass(frozen=True)
class CameraCounters:
    """A camera's evidence counters as a write transaction left them: what decides whether a solve is due."""

    epoch: int
    usable_evidence_count: int
    evidence_at_last_solve: int


class StoredCentres(Protocol):
    """A stored person's centres: an Observation, or a light row from service.frames.repository.frames_points."""

    shoulder_x_px: float | None
    shoulder_y_px: float | None
    ankle_x_px: float | None
    ankle_y_px: float | None
    unusable_reason: str | None
    """Why the person is not calibration evidence (None: they are), in words."""
    client_track_id: str | None
    """The client's track id, as posted (None when none was): echoed with the person's result."""
    posture: str | None
    """`PersonIn.posture` as stored."""
    placed_from_box: bool
    static: bool


def track_id_of(person: PersonIn | StoredCentres) -> str | None:
    """The client's track id of a person not yet stored, or of a stored one."""
    return person.track_id if isinstance(person, PersonIn) else person.client_track_id


def centres(person: PersonIn | StoredCentres) -> tuple[Point | None, Point | None]:
    """(shoulder, ankle) pixels of a person not yet stored, or of a stored one."""
    if isinstance(person, PersonIn):
        return person.shoulder_px, person.ankle_px
    shoulder = None if person.shoulder_x_px is None else (person.shoulder_x_px, person.shoulder_y_px)
    ankle = None if person.ankle_x_px is None else (person.ankle_x_px, person.ankle_y_px)
    return shoulder, ankle  # type: ignore[return-value]


@dataclass(frozen=True)
class ViolationIn:
    """A pair of people (indices into the frame's people) closer than the camera's threshold.

    Where each of the two stands on the ground (the result's `ground_m`) and their client track ids travel with
    the pair for the `violation.detected` webhook (its cooldown places pairs on the ground), so raising it does not
    parse the frame's stored result back inside the measuring job's transaction; only the first four are stored.
    """

    person_i: int
    person_j: int
    distance_m: float
    distance_std_m: float | None = None
    ground_i_m: tuple[float, float] | None = None
    ground_j_m: tuple[float, float] | None = None
    track_id_i: str | None = None
    track_id_j: str | None = None


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
    camera_model: dict[str, Any] | None = None
    """Lens, ankle height, size-dependent noise, sources and inputs (service.calibration.camera_model)."""
    quality: dict[str, Any] | None = None
    """What the calibration is worth (service.geometry.quality), as stored."""

    @property
    def quality_grade(self) -> str | None:
        return None if self.quality is None else self.quality.get("grade")

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
            covariance=None if unc is None else [[float(v) for v in row] for row in unc.covariance],
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
