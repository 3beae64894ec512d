"""The result type of calibrate(): camera, ground plane, placed people, uncertainties."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .vec import FloatArray


@dataclass(frozen=True)
class Uncertainty:
    """1-sigma uncertainties of the calibration (Gauss-Newton covariance at the solution)."""

    fx_px: float
    fy_px: float
    normal_deg: float  # RMS angle between the estimated and the true normal
    rho_m: float
    # 5x5 over (fx_px, fy_px, t1_rad, t2_rad, rho_m): see uncertainty.CANONICAL_PARAMETERS.
    covariance: FloatArray
    noise_px: float  # keypoint noise estimated from the residuals


@dataclass(frozen=True)
class Calibration:
    """A solved camera: K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] and ground N . X + rho = 0.

    Camera frame x right, y down, z forward; normal is a unit vector pointing up;
    rho (metres) is the camera centre's height above the ground. Per-person arrays
    follow the input order; rejected people have NaN rows and inliers False.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    normal: FloatArray
    rho: float
    image_size: tuple[float, float]
    height_m: float
    points_bottom: FloatArray
    points_top: FloatArray
    heights: FloatArray
    inliers: FloatArray
    uncertainty: Uncertainty | None = None
    # Division model u = u_d / (1 + k |u_d|^2) on frame-normalised coordinates
    # u = (x - c) / ((W + H) / 4); see service.geometry.camera.
    distortion_k: float = 0.0
    refined: bool = False
    ransac_iterations: int = 0
    reprojection_rms_px: float = float("nan")

    @property
    def camera(self) -> Camera:
        return Camera(self.fx, self.fy, self.cx, self.cy, self.image_size, self.distortion_k)

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))
