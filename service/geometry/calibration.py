"""The result type of calibrate(): camera, ground plane, placed people, uncertainties, and where each came from."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from .camera import Camera, OpenCVLens
from .vec import FloatArray

Source = Literal["given", "estimated", "assumed"]
"""given: the user's value, exact; estimated: determined by the people (with its sigma); assumed: a default
the people do not determine (image centre, square pixels, no distortion), carried with the prior's sigma."""

Grade = Literal["good", "rough", "unreliable"]
"""What a calibration is worth (service.geometry.quality decides it)."""


@dataclass(frozen=True)
class Quality:
    """What a calibration is worth: its grade, the error it predicts, and what would help (see quality.assess)."""

    grade: Grade
    distance_2sigma_m: float
    """Predicted 2-sigma error of a 2 m distance at the typical range (NaN when it cannot be predicted)."""
    typical_range_m: float
    """Median ground distance of the calibration's people from the point below the camera."""
    reasons: tuple[str, ...]
    """Why the grade is not `good` (empty when it is)."""
    advice: tuple[str, ...]
    """What would improve it."""
    people_needed: int
    """How many more distinct people would bring the evidence to a well-sampled crowd (0: enough)."""


@dataclass(frozen=True)
class Uncertainty:
    """1-sigma uncertainties of the calibration (the posterior's Gauss-Newton covariance at the solution)."""

    fx_px: float
    fy_px: float
    normal_deg: float  # RMS angle between the estimated and the true normal
    rho_m: float
    # Over uncertainty.CANONICAL_PARAMETERS (fx_px, fy_px, t1_rad, t2_rad, rho_m, cx_px, cy_px, k); a 5x5
    # covariance (stored before the principal point had one) covers the first five.
    covariance: FloatArray
    noise_px: float  # keypoint noise estimated from the residuals (the size-independent part)
    cx_px: float = 0.0
    cy_px: float = 0.0
    distortion_k: float = 0.0
    # Keypoint noise that grows with a person's size (pose-model error, lean): sigma_o^2 = noise_px^2 +
    # (noise_per_length * segment length)^2.
    noise_per_length: float = 0.0


@dataclass(frozen=True)
class Calibration:
    """A solved camera: K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], its lens, and the plane N . X + rho = 0.

    Camera frame x right, y down, z forward; normal is a unit vector pointing up. The plane is the one the
    people's ankle keypoints stand on: rho (metres) is the camera centre's height above it, and
    camera_height_m (rho + ankle_height_m) its height above the ground. Per-person arrays follow the input
    order; rejected people have NaN rows and inliers False.
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
    # u = (x - c) / ((W + H) / 4) about the principal point; see service.geometry.camera.
    distortion_k: float = 0.0
    refined: bool = False
    ransac_iterations: int = 0
    reprojection_rms_px: float = float("nan")
    # The user's OpenCV lens (keypoints were undistorted with it before solving).
    lens: OpenCVLens | None = None
    ankle_height_m: float = 0.0
    principal_point_source: Source = "assumed"
    focal_source: Source = "estimated"
    distortion_source: Source = "assumed"
    # Distinct individuals among the inliers (observations of one person in many frames count once).
    individuals: int = 0
    # What the calibration is worth (service.geometry.quality); None without an uncertainty.
    quality: Quality | None = None

    @property
    def camera(self) -> Camera:
        return Camera(self.fx, self.fy, self.cx, self.cy, self.image_size, self.distortion_k, self.lens)

    @property
    def camera_height_m(self) -> float:
        """The camera centre's height above the ground (the plane of the ankles lies ankle_height_m above it)."""
        return self.rho + self.ankle_height_m

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))
