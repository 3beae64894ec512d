"""What a calibration is asked: what is known about the camera and the people (the problem), and how to solve it.

A problem is checked when it is made, so a bad value fails with a clear CalibrationError before any work.

The camera model users have (issue 16): a principal point, a focal length (one value or fx, fy), OpenCV
lens coefficients and an installer-known camera height are each optional. What is not given is estimated
where the people determine it and otherwise carried as a prior whose spread reaches every figure:

* principal point: N(image centre, PRINCIPAL_POINT_STD_FRACTION x image height) per axis. Published
  calibrations of real cameras put the principal point 0-5 % of the image height from the centre (verified
  values, offset / height: KITTI P2 1242x375 (609.6, 172.9): 3.0 %, 3.9 %; nuScenes CAM_FRONT 1600x900
  (816.3, 491.5): 1.8 %, 4.6 %; Cityscapes 2048x1024 (1079.0, 515.0): 5.4 %, 0.3 %; TUM RGB-D fr1 640x480
  (318.6, 255.3): 0.2 %, 3.2 %; EuRoC cam0 752x480 (367.2, 248.4): 1.8 %, 1.8 %; Oxford Town Centre
  1920x1080 (959.5, 539.5): 0 %; RMS 2.8 % per axis), while streams cropped or shifted in the camera
  (digital PTZ, corridor modes, re-framed encodes) move it much further: the held-out surveillance layouts
  of issue 16 sit 75-180 px off centre (7-17 % of 1080). 9 % per axis puts the sensor-centred population
  inside 1 sigma and the held-out layouts' 17 % inside 1.9 sigma. A Gaussian whose spread is the mixture's
  RMS (7.5 %: a third of cameras cropped) under-covers that tail: on the realistic simulator with offsets up to
  17 %, the cameras 12-17 % off had f and the normal within 2 sigma on 84 % and 84 % at 7.5 %, on 91 % and 90 %
  at 9 % (docs/benchmarks/camera-model.md), for a sigma of f 8 % wider on a typical camera.
* square pixels: fy/fx = 1 with a 1 % prior (real sensors: Cityscapes 0.6 %, EuRoC 0.3 %, TUM 0.15 %).
* the population's mean ankle-to-shoulder height: height_m with a 4 % prior (national means of adult
  stature differ by about that much between populations, and crowds mix sexes and ages).
* the pose model's keypoint bias along the body: 0.2 % of the image height (2 px at 1080p), a constant
  pixel offset that weighs more on small, far people (it moves the apparent horizon).
* lens distortion too small to detect: people lean and pose models err by a few percent of a person's
  size, so a radial distortion that moves the image corner by less than ~6 % of its radius bends the
  segments less than that noise (on the realistic simulator the evidence test rarely fires below it). It is
  carried as a 3 % (1-sigma) corner shift; larger lenses are detected and estimated (service.geometry.distortion).
  Wider than a 35 deg half-diagonal (tan^2 > LENS_WIDE_TAN2 = 0.5, a 38 deg vertical field of view at 16:9) the spread
  grows with tan^2 of the half-diagonal field of view, as a lens design's corner shift does: 6 % at tan^2 = 1,
  9 % at 1.5. Real wide lenses bend far more than 3 % (datasheets: an M12 3.9 mm lens on a 1/2.7" sensor, 104
  deg diagonal, -34 % optical distortion, 0.47 tan^2; a 5-100 mm zoom on 1/2.8" at its wide end, 66.5 deg,
  -9.7 %, 0.27 tan^2; +2.1 % at 100 mm), and on wide views (60-90 deg vertically) the evidence test misses
  most 3-15 % corner shifts: held at 3 %, f, the normal and the camera height were within 2 sigma on 87, 84 and
  90 % of 400 such simulated cameras; with the wider spread 90, 91 and 96 % (docs/benchmarks/camera-model.md). A
  very wide view seen through few people may then be refused: its f is not determined once its lens may be that
  strong (the paper's 90 x 90 deg camera with 21 inliers: 6 of 3000 scenes, f +-29-42 % before, over 50 % now).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import OpenCVLens
from .errors import CalibrationError
from .priors import DEFAULT_ANKLE_HEIGHT_M, DEFAULT_HEIGHT_M, DEFAULT_HEIGHT_STD_M

PRINCIPAL_POINT_STD_FRACTION = 0.09
ASPECT_STD = 0.01
MEAN_HEIGHT_STD_FRACTION = 0.04
KEYPOINT_BIAS_STD_FRACTION = 0.002
LENS_CORNER_STD_FRACTION = 0.03
LENS_WIDE_TAN2 = 0.5


def _positive_pair(name: str, value: object) -> tuple[float, float]:
    try:
        pair = np.broadcast_to(np.asarray(value, dtype=np.float64), (2,))
    except (TypeError, ValueError):
        raise CalibrationError(f"{name} must be one or two numbers, got {value!r}") from None
    if not (np.all(np.isfinite(pair)) and np.all(pair > 0)):
        raise CalibrationError(f"{name} must be positive, got {value!r}")
    return float(pair[0]), float(pair[1])


def _non_negative(name: str, value: float) -> None:
    if not (np.isfinite(value) and value >= 0):
        raise CalibrationError(f"{name} must be a non-negative number, got {value!r}")


@dataclass(frozen=True)
class CalibrationProblem:
    """The camera's image and what is known about it and about the people seen through it."""

    image_size_px: tuple[float, float]
    height_m: float = DEFAULT_HEIGHT_M
    """Ankle-centre-to-shoulder-centre height prior: sets the metric scale."""
    height_std_m: float = DEFAULT_HEIGHT_STD_M
    """Spread of individual heights around the population's mean."""
    equal_focal: bool = True
    """Square pixels (fx = fy up to ASPECT_STD), or fx and fy free."""
    principal_point_px: tuple[float, float] | None = None
    """Given: exact. None: the image centre as a prior (principal_point_std)."""
    focal_px: float | tuple[float, float] | None = None
    """A known focal length (one value, or fx and fy): then only the ground plane is solved."""
    lens: OpenCVLens | None = None
    """Given OpenCV lens coefficients: keypoints are undistorted with them before solving."""
    camera_height_m: float | None = None
    """An installer-known height of the camera above the ground, a constraint on scale..."""
    camera_height_std_m: float = 0.1
    """... with this tolerance (1-sigma)."""
    principal_point_std: float = PRINCIPAL_POINT_STD_FRACTION
    """Prior spread of the principal point per axis, as a fraction of the image height."""
    aspect_std: float = ASPECT_STD
    """Prior spread of fy/fx around 1 with square pixels; 0: exactly square."""
    mean_height_std: float = MEAN_HEIGHT_STD_FRACTION
    """Prior spread of the population's mean height, relative; 0: height_m is exact."""
    keypoint_bias_std: float = KEYPOINT_BIAS_STD_FRACTION
    """Prior spread of the pose model's keypoint bias along the body, as a fraction of the image height; 0: none."""
    lens_corner_std: float = LENS_CORNER_STD_FRACTION
    """Prior spread of undetected radial distortion, as the shift of the image corner over its radius, for views up
    to LENS_WIDE_TAN2 (tan^2 of the half-diagonal field of view); wider views scale it by tan^2 / LENS_WIDE_TAN2
    (`lens_corner_spread`). 0: none."""
    ankle_height_m: float = DEFAULT_ANKLE_HEIGHT_M
    """Height of the ankle keypoints above the ground (the ground lies this far below their plane)."""

    def __post_init__(self) -> None:
        try:
            width, height = float(self.image_size_px[0]), float(self.image_size_px[1])
        except (TypeError, ValueError, IndexError):
            raise CalibrationError(f"image_size must be (width, height), got {self.image_size_px!r}") from None
        if not (np.isfinite(width) and np.isfinite(height) and width > 0 and height > 0):
            raise CalibrationError(f"image_size must be two positive numbers, got {self.image_size_px!r}")
        if not (np.isfinite(self.height_m) and self.height_m > 0):
            raise CalibrationError(f"height must be a positive number of metres, got {self.height_m!r}")
        if not (np.isfinite(self.height_std_m) and self.height_std_m > 0):
            raise CalibrationError(f"height_std_m must be a positive number of metres, got {self.height_std_m!r}")
        if self.focal_px is not None:
            _positive_pair("focal_px", self.focal_px)
        if self.principal_point_px is not None:
            pp = np.asarray(self.principal_point_px, dtype=np.float64)
            if pp.shape != (2,) or not np.all(np.isfinite(pp)):
                raise CalibrationError(
                    f"principal_point_px must be two finite numbers, got {self.principal_point_px!r}"
                )
        if self.camera_height_m is not None:
            if not (np.isfinite(self.camera_height_m) and self.camera_height_m > 0):
                raise CalibrationError(f"camera_height_m must be positive, got {self.camera_height_m!r}")
            if not (np.isfinite(self.camera_height_std_m) and self.camera_height_std_m > 0):
                raise CalibrationError(f"camera_height_std_m must be positive, got {self.camera_height_std_m!r}")
        for name in (
            "principal_point_std",
            "aspect_std",
            "mean_height_std",
            "keypoint_bias_std",
            "lens_corner_std",
            "ankle_height_m",
        ):
            _non_negative(name, getattr(self, name))

    @property
    def known_focal_px(self) -> tuple[float, float] | None:
        return None if self.focal_px is None else _positive_pair("focal_px", self.focal_px)

    def lens_corner_spread(self, half_diagonal_tan: float) -> float:
        """The undetected lens's prior spread (corner shift over corner radius) for a camera whose image corner lies
        half_diagonal_tan focal lengths from the image centre (module docstring)."""
        return self.lens_corner_std * max(1.0, half_diagonal_tan**2 / LENS_WIDE_TAN2)


@dataclass(frozen=True)
class SolveOptions:
    """How to solve. The defaults are the most accurate pipeline: RANSAC, then the MAP refinement with its
    covariance, lens distortion estimated where the evidence supports it."""

    robust: bool | None = None
    """RANSAC (None: yes)."""
    refine: bool | None = None
    """The MAP refinement (None: yes)."""
    uncertainty: bool = True
    """False skips the covariance (only useful when nothing but the point estimate is wanted, fast)."""
    distortion: bool = True
    """Estimate one-parameter division-model lens distortion when the evidence supports it (see
    service.geometry.lens); False: assume none. Ignored when the problem gives a lens."""
    seed: int | None = 0
    inlier_px: float | None = None
    """RANSAC's direction threshold; None: 0.3 % of the image diagonal."""
    height_tolerance: float = 0.2
    """RANSAC's relative height threshold."""
    max_iterations: int = 5000
