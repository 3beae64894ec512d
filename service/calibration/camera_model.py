"""The camera model between a camera's settings, the geometry and the store (issue 16).

Three translations, each defined once:

* `problem_for`: a camera's settings (principal point, focal length, lens, camera height, person height) as the
  geometry's CalibrationProblem, which the calibration worker solves;
* `model_record` / `quality_record`: what a solve found about the camera model, as the JSON a calibration version
  stores: everything measuring with the version needs (lens, ankle height, size-dependent keypoint noise, the
  covariance's parameter names) and what the responses show (where the principal point, focal length and
  distortion came from, with their sigma; the inputs the solve was given; the quality grade);
* `calibration_from_version`: a stored version back as the geometry's Calibration, so a distance measured later has
  the sigma the solve had (a version that lost its lens, ankle height or size-dependent noise would understate
  `distance_std_m`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from service.cameras.schemas import DEFAULT_CAMERA_HEIGHT_TOLERANCE_M
from service.geometry import Calibration, CalibrationProblem, OpenCVLens, Quality, Uncertainty
from service.geometry.uncertainty import CANONICAL_PARAMETERS
from service.store.models import CalibrationVersion, Camera, finite_or_none


def known_focal(camera: Camera) -> float | tuple[float, float] | None:
    """The camera's known focal length as its settings give it: one value, [fx, fy], or None."""
    if camera.known_focal_px is None:
        return None
    if camera.known_focal_y_px is None:
        return float(camera.known_focal_px)
    return (float(camera.known_focal_px), float(camera.known_focal_y_px))


def principal_point(camera: Camera) -> tuple[float, float] | None:
    if camera.principal_point_x_px is None or camera.principal_point_y_px is None:
        return None
    return (float(camera.principal_point_x_px), float(camera.principal_point_y_px))


def lens_of(camera: Camera) -> OpenCVLens | None:
    coefficients = camera.distortion_coefficients
    return None if not coefficients else OpenCVLens.from_coefficients(coefficients)


def problem_for(camera: Camera) -> CalibrationProblem:
    """The calibration problem a camera's settings pose (CalibrationError for values the geometry refuses)."""
    tolerance_m = camera.camera_height_tolerance_m
    return CalibrationProblem(
        (camera.image_width_px, camera.image_height_px),
        camera.person_height_m,
        equal_focal=camera.equal_focal,
        focal_px=known_focal(camera),
        principal_point_px=principal_point(camera),
        lens=lens_of(camera),
        camera_height_m=camera.camera_height_m,
        camera_height_std_m=DEFAULT_CAMERA_HEIGHT_TOLERANCE_M if tolerance_m is None else float(tolerance_m),
    )


def inputs_record(problem: CalibrationProblem) -> dict[str, Any]:
    """What a solve was given, as stored with its version (None: not given, so estimated or assumed)."""
    focal, lens = problem.known_focal_px, problem.lens
    return {
        "principal_point_px": None if problem.principal_point_px is None else list(problem.principal_point_px),
        "known_focal_px": None if focal is None else list(focal),
        "distortion": None if lens is None else {"model": "opencv", "coefficients": list(lens.coefficients)},
        "camera_height_m": problem.camera_height_m,
        "camera_height_tolerance_m": problem.camera_height_std_m if problem.camera_height_m is not None else None,
        "person_height_m": problem.height_m,
        "equal_focal": problem.equal_focal,
    }


def _std(unc: Uncertainty | None, name: str) -> float | None:
    return None if unc is None else finite_or_none(getattr(unc, name))


def model_record(cal: Calibration, problem: CalibrationProblem) -> dict[str, Any]:
    """A solve's camera model as a calibration version stores it (JSON-ready, non-finite numbers as null)."""
    unc = cal.uncertainty
    if cal.lens is not None:
        distortion: dict[str, Any] = {"model": "opencv", "coefficients": list(cal.lens.coefficients)}
    else:
        distortion = {"model": "division", "division_k": finite_or_none(cal.distortion_k)}
    distortion.update(source=cal.distortion_source, division_k_std=_std(unc, "distortion_k"))
    covariance_size = 0 if unc is None else len(unc.covariance)
    return {
        "principal_point": {
            "source": cal.principal_point_source,
            "cx_px": finite_or_none(cal.cx),
            "cy_px": finite_or_none(cal.cy),
            "cx_std_px": _std(unc, "cx_px"),
            "cy_std_px": _std(unc, "cy_px"),
        },
        "focal_length": {
            "source": cal.focal_source,
            "fx_px": finite_or_none(cal.fx),
            "fy_px": finite_or_none(cal.fy),
            "fx_std_px": _std(unc, "fx_px"),
            "fy_std_px": _std(unc, "fy_px"),
        },
        "distortion": distortion,
        "camera_height_m": finite_or_none(cal.camera_height_m),
        "ankle_height_m": float(cal.ankle_height_m),
        "noise_per_length": None if unc is None else finite_or_none(unc.noise_per_length),
        "individuals": int(cal.individuals),
        "covariance_parameters": list(CANONICAL_PARAMETERS[:covariance_size]),
        "inputs": inputs_record(problem),
    }


def quality_record(quality: Quality | None) -> dict[str, Any] | None:
    if quality is None:
        return None
    return {
        "grade": quality.grade,
        "distance_2sigma_m": finite_or_none(quality.distance_2sigma_m),
        "typical_range_m": finite_or_none(quality.typical_range_m),
        "reasons": list(quality.reasons),
        "advice": list(quality.advice),
        "people_needed": int(quality.people_needed),
    }


def _number(record: dict[str, Any], *path: str) -> float:
    value: Any = record
    for key in path:
        value = value.get(key) if isinstance(value, dict) else None
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else 0.0


def calibration_from_version(version: CalibrationVersion, image_size_px: tuple[int, int]) -> Calibration:
    """The geometry's Calibration for a stored version, enough for `measure` (per-person arrays are empty).

    The stored covariance is over the canonical parameters its camera model names (eight; five for versions
    stored before the principal point had a sigma); a version without a complete covariance gets no Uncertainty,
    so distances then carry keypoint noise only. The lens, the ankle height and the size-dependent keypoint noise
    come from the stored camera model (a version stored without one had none of them).
    """
    if version.status != "ok" or None in (version.fx_px, version.fy_px, version.cx_px, version.cy_px, version.rho_m):
        raise ValueError(f"calibration version {version.version} has no solved camera (status {version.status})")
    record = version.camera_model or {}
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
            cx_px=_number(record, "principal_point", "cx_std_px"),
            cy_px=_number(record, "principal_point", "cy_std_px"),
            distortion_k=_number(record, "distortion", "division_k_std"),
            noise_per_length=_number(record, "noise_per_length"),
        )
    distortion = record.get("distortion") or {}
    lens = None
    if distortion.get("model") == "opencv" and distortion.get("coefficients"):
        lens = OpenCVLens.from_coefficients(distortion["coefficients"])
    normal = np.array([version.normal_x, version.normal_y, version.normal_z], dtype=float)
    sources = {
        name: record[key]["source"]
        for name, key in (
            ("principal_point_source", "principal_point"),
            ("focal_source", "focal_length"),
            ("distortion_source", "distortion"),
        )
        if isinstance(record.get(key), dict) and record[key].get("source") in ("given", "estimated", "assumed")
    }
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
        lens=lens,
        ankle_height_m=_number(record, "ankle_height_m"),
        individuals=int(record.get("individuals") or 0),
        **sources,  # type: ignore[arg-type]
    )
