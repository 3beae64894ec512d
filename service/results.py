"""A frame's result (positions, pair distances, violations) from its people and a stored calibration.

Shared by the synchronous `POST .../distances` endpoint and the frame-processing worker, so that a frame's
stored result and an on-demand measurement of the same people are computed by the same code. No I/O: the
caller reads the calibration and the people from the store and writes the outcome back (the worker does that a
batch of frames at a time; `process_frame` does it for one frame in the caller's transaction).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import pydantic_core
from sqlalchemy.orm import Session

from service.geometry import Calibration, Uncertainty, measure
from service.schemas import FrameResult
from service.store import repository
from service.store.db import EncodedJSON
from service.store.models import CalibrationVersion, Camera, Frame, clip_reason
from service.store.repository import FrameOutcome, PersonIn, ViolationIn

Point = tuple[float, float]
_NAN_POINT = (math.nan, math.nan)


@dataclass(frozen=True)
class FrameComputation:
    """What measuring a frame produced: the result (as a JSON-ready document) and the violation rows for the store.

    The document is built here from plain numbers, in FrameResult's shape; the worker stores it as it is, and a
    FrameResult model is made only where one is needed (an HTTP answer, the offline writers). Validating 190
    pairs per frame in the worker cost as much as measuring them, and proved nothing the tests do not.
    """

    document: dict[str, Any]
    violations: list[ViolationIn]

    @property
    def result(self) -> FrameResult:
        return FrameResult.model_validate(self.document)

    def result_json(self) -> EncodedJSON:
        """The result as stored in `frames.result`, encoded now: in Rust (pydantic-core), five times faster than the
        json module for a frame's 190 pairs. Non-finite numbers are already None; any left would be null."""
        return EncodedJSON(pydantic_core.to_json(self.document, inf_nan_mode="null").decode())


def calibration_from_version(version: CalibrationVersion, image_size_px: tuple[int, int]) -> Calibration:
    """The geometry's Calibration for a stored version, enough for `measure` (per-person arrays are empty).

    The stored covariance is the geometry's canonical 5x5 one; a version without a complete covariance gets no
    Uncertainty, so distances then carry keypoint noise only (its noise estimate is passed to measure separately).
    """
    if version.status != "ok" or None in (version.fx_px, version.fy_px, version.cx_px, version.cy_px, version.rho_m):
        raise ValueError(f"calibration version {version.version} has no solved camera (status {version.status})")
    uncertainty = None
    cov = version.covariance
    if cov is not None and all(v is not None for row in cov for v in row):
        uncertainty = Uncertainty(
            fx_px=version.fx_std_px or 0.0,
            fy_px=version.fy_std_px or 0.0,
            normal_deg=version.normal_std_deg or 0.0,
            rho_m=version.rho_std_m or 0.0,
            covariance=np.asarray(cov, dtype=float),
            noise_px=version.noise_px or 0.0,
        )
    normal = np.array([version.normal_x, version.normal_y, version.normal_z], dtype=float)
    return Calibration(
        fx=float(version.fx_px),  # type: ignore[arg-type]
        fy=float(version.fy_px),  # type: ignore[arg-type]
        cx=float(version.cx_px),  # type: ignore[arg-type]
        cy=float(version.cy_px),  # type: ignore[arg-type]
        normal=normal / np.linalg.norm(normal),
        rho=float(version.rho_m),  # type: ignore[arg-type]
        image_size=(float(image_size_px[0]), float(image_size_px[1])),
        height_m=float(version.person_height_m),
        points_bottom=np.zeros((0, 3)),
        points_top=np.zeros((0, 3)),
        heights=np.zeros(0),
        inliers=np.zeros(0, dtype=bool),
        uncertainty=uncertainty,
        distortion_k=float(version.distortion_k or 0.0),
    )


class StoredCentres(Protocol):
    """A stored person's centres: an Observation, or a light row from `repository.frames_points`."""

    shoulder_x_px: float | None
    shoulder_y_px: float | None
    ankle_x_px: float | None
    ankle_y_px: float | None


def _points(person: StoredCentres | PersonIn) -> tuple[Point | None, Point | None]:
    """(shoulder, ankle) pixels of a stored person or of a not-yet-stored one."""
    if isinstance(person, PersonIn):
        return person.shoulder_px, person.ankle_px
    shoulder = None if person.shoulder_x_px is None else (person.shoulder_x_px, person.shoulder_y_px)
    ankle = None if person.ankle_x_px is None else (person.ankle_x_px, person.ankle_y_px)
    return shoulder, ankle  # type: ignore[return-value]


def _ground_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(right, forward) unit vectors on the ground: the viewing direction projected onto it, and its right."""
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, normal)
    return right, forward


def compute_frame_result(
    people: Sequence[StoredCentres | PersonIn],
    calibration: CalibrationVersion,
    *,
    image_size_px: tuple[int, int],
    distance_threshold_m: float,
) -> FrameComputation:
    """A frame's result with a stored calibration version (see `measure_people`)."""
    return measure_people(
        people,
        calibration_from_version(calibration, image_size_px),
        distance_threshold_m=distance_threshold_m,
        calibration_version=calibration.version,
        noise_px=calibration.noise_px or 0.0,
    )


def measure_people(
    people: Sequence[StoredCentres | PersonIn],
    cal: Calibration,
    *,
    distance_threshold_m: float,
    calibration_version: int = 0,
    noise_px: float | None = None,
) -> FrameComputation:
    """Place every person (ankles when seen, else shoulders), measure all pairs i < j, and flag violations.

    A pair is a violation when its distance is strictly below `distance_threshold_m`; pairs involving a person
    who could not be placed (no shoulder and no ankle, or a ray missing the ground) have null distances and are
    never violations. `noise_px` is the keypoint noise for the distance uncertainties (default: the one the
    calibration estimated).
    """
    points = [_points(person) for person in people]
    tops = np.array([s if s is not None else _NAN_POINT for s, _ in points], dtype=float).reshape(-1, 2)
    bottoms = np.array([a if a is not None else _NAN_POINT for _, a in points], dtype=float).reshape(-1, 2)
    n = len(points)
    if n:
        m = measure(cal, tops, bottoms, noise_px=noise_px)
        positions, distances, stds = m.points_bottom, m.distances_m, m.distance_std_m
    else:
        positions, distances, stds = np.zeros((0, 3)), np.zeros((0, 0)), np.zeros((0, 0))
    foot = -cal.rho * cal.normal  # the point on the ground straight below the camera
    right, forward = _ground_axes(cal.normal)
    placed = np.all(np.isfinite(positions), axis=1)
    ground = np.stack(((positions - foot) @ right, (positions - foot) @ forward), -1)
    placed_people = [
        {
            "index": index,
            "placed_from": ("ankles" if points[index][1] is not None else "shoulders") if is_placed else None,
            "ground_m": ground_m if is_placed else None,
            "point_m": point_m if is_placed else None,
        }
        for index, (is_placed, ground_m, point_m) in enumerate(
            zip(placed.tolist(), ground.tolist(), positions.tolist(), strict=True)
        )
    ]
    # Pairs i < j, from plain Python values: a frame of 20 people has 190 pairs.
    first, second = np.triu_indices(n, 1)
    pair_m, pair_std_m = distances[first, second], stds[first, second]
    known = np.isfinite(pair_m)
    pairs = [
        {"i": i, "j": j, "distance_m": d if ok else None, "distance_std_m": sd if ok and math.isfinite(sd) else None}
        for i, j, d, sd, ok in zip(
            first.tolist(), second.tolist(), pair_m.tolist(), pair_std_m.tolist(), known.tolist(), strict=True
        )
    ]
    close = [pair for pair in pairs if pair["distance_m"] is not None and pair["distance_m"] < distance_threshold_m]
    violations = [
        ViolationIn(person_i=p["i"], person_j=p["j"], distance_m=p["distance_m"], distance_std_m=p["distance_std_m"])
        for p in close
    ]
    document = {
        "calibration_version": calibration_version,
        "distance_threshold_m": distance_threshold_m,
        "people": placed_people,
        "pairs": pairs,
        "violations": close,
    }
    return FrameComputation(document=document, violations=violations)


def frame_outcome(
    frame: Frame, people: Sequence[StoredCentres], camera: Camera, calibration: CalibrationVersion
) -> FrameOutcome:
    """A stored frame measured with `calibration`: done with its result, or failed with the reason (no I/O).

    Bad stored data for one frame (a person the geometry refuses) fails that frame, not the worker's batch.
    """
    try:
        computation = compute_frame_result(
            people,
            calibration,
            image_size_px=(camera.image_width_px, camera.image_height_px),
            distance_threshold_m=camera.distance_threshold_m,
        )
    except (ValueError, ArithmeticError) as exc:
        return FrameOutcome(
            frame.id, frame.camera_id, frame.timestamp, "failed", calibration.version, error=clip_reason(str(exc))
        )
    return FrameOutcome(
        frame.id,
        frame.camera_id,
        frame.timestamp,
        "done",
        calibration.version,
        result=computation.result_json(),
        violations=computation.violations,
    )


def process_frame(session: Session, frame: Frame, camera: Camera, calibration: CalibrationVersion) -> FrameOutcome:
    """Measure one stored frame and store its result and violation events in the caller's transaction."""
    outcome = frame_outcome(frame, repository.frame_observations(session, frame.id), camera, calibration)
    repository.record_frame_outcomes(session, [outcome])
    return outcome
