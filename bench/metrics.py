"""How far a calibration is from a simulated scene's truth: the paper's metrics (Sect. 4.1) and one trial's result."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bench.simulate import Scene
from service.geometry import Calibration

FloatArray = NDArray[np.float64]

METRIC_KEYS: Final = ("fx_pct", "fy_pct", "normal_deg", "rho_pct", "points_pct", "dist_pct", "dist_m")
EXTRA_KEYS: Final = ("inliers_placed_pct", "outliers_placed_pct")


def relative_error_pct(estimate: float, truth: float) -> float:
    return 100.0 * abs(estimate - truth) / abs(truth)


def angle_deg(a: ArrayLike, b: ArrayLike) -> float:
    """Angle between two vectors; atan2 keeps full precision near 0, where arccos of the dot product loses ~8 digits."""
    u, v = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(u, v))), float(u @ v)))


def point_errors_pct(estimate: FloatArray, truth: FloatArray) -> FloatArray:
    """Per-point ||X^ - X|| / ||X||: normalised so near and far people weigh the same (paper Sect. 4.1)."""
    return 100.0 * np.linalg.norm(estimate - truth, axis=-1) / np.linalg.norm(truth, axis=-1)


def distance_errors(estimate: FloatArray, truth: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(|d^ - d| / d in %, |d^ - d| in metres) over every unordered pair of people."""
    i, j = np.triu_indices(len(truth), k=1)
    d_true = np.linalg.norm(truth[i] - truth[j], axis=-1)
    d_est = np.linalg.norm(estimate[i] - estimate[j], axis=-1)
    err_m = np.abs(d_est - d_true)
    return 100.0 * err_m / d_true, err_m


@dataclass(frozen=True)
class TrialResult:
    """One calibrate() call on one scene. metrics holds METRIC_KEYS and EXTRA_KEYS; NaN where undefined."""

    metrics: Mapping[str, float] = field(default_factory=dict)
    failed: bool = False
    error: str = ""
    # An exception other than CalibrationError: a bug to report, not a failure of the method.
    unexpected: bool = False

    @classmethod
    def failure(cls, error: str, unexpected: bool = False) -> TrialResult:
        return cls({k: math.nan for k in (*METRIC_KEYS, *EXTRA_KEYS)}, True, error, unexpected)


def true_outliers(scene: Scene) -> NDArray[np.bool_]:
    n = len(scene.points_bottom)
    outliers = np.asarray(scene.outliers, dtype=bool)
    return outliers if outliers.shape == (n,) else np.zeros(n, dtype=bool)


def evaluate(scene: Scene, cal: Calibration) -> TrialResult:
    """Errors of a Calibration against the scene's truth.

    People the scene made outliers have no true position on the model, so they
    never enter the point or distance errors; of the rest, only those the
    calibration placed count (how many it placed is reported separately).
    """
    normal = np.asarray(cal.normal, dtype=np.float64)
    camera = np.array([cal.fx, cal.fy, cal.rho, *normal], dtype=np.float64)
    if not np.all(np.isfinite(camera)):
        return TrialResult.failure("non-finite camera")
    outliers = true_outliers(scene)
    x_b, x_t = np.asarray(cal.points_bottom, dtype=np.float64), np.asarray(cal.points_top, dtype=np.float64)
    placed = np.asarray(cal.inliers, dtype=bool) & np.all(np.isfinite(x_b), axis=1) & np.all(np.isfinite(x_t), axis=1)
    use = placed & ~outliers
    if not use.any():
        return TrialResult.failure("no true inlier placed")
    points = np.concatenate(
        (point_errors_pct(x_b[use], scene.points_bottom[use]), point_errors_pct(x_t[use], scene.points_top[use]))
    )
    dist_pct, dist_m = distance_errors(x_b[use], scene.points_bottom[use])
    metrics = {
        "fx_pct": relative_error_pct(cal.fx, scene.fx),
        "fy_pct": relative_error_pct(cal.fy, scene.fy),
        "normal_deg": angle_deg(normal, scene.normal),
        "rho_pct": relative_error_pct(cal.rho, scene.rho),
        "points_pct": float(points.mean()),
        "dist_pct": float(dist_pct.mean()) if dist_pct.size else math.nan,
        "dist_m": float(dist_m.mean()) if dist_m.size else math.nan,
        "inliers_placed_pct": 100.0 * use.sum() / max(int((~outliers).sum()), 1),
        "outliers_placed_pct": 100.0 * (placed & outliers).sum() / outliers.sum() if outliers.any() else math.nan,
    }
    if not all(math.isfinite(metrics[k]) for k in ("fx_pct", "fy_pct", "normal_deg", "rho_pct", "points_pct")):
        return TrialResult.failure("non-finite result")
    return TrialResult(metrics)
