"""What a calibration is asked: what is known about the camera and the people (the problem), and how to solve it.

A problem is checked when it is made, so a bad value fails with a clear CalibrationError before any work.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import CalibrationError
from .priors import DEFAULT_HEIGHT_M, DEFAULT_HEIGHT_STD_M


def _positive_pair(name: str, value: object) -> tuple[float, float]:
    try:
        pair = np.broadcast_to(np.asarray(value, dtype=np.float64), (2,))
    except (TypeError, ValueError):
        raise CalibrationError(f"{name} must be one or two numbers, got {value!r}") from None
    if not (np.all(np.isfinite(pair)) and np.all(pair > 0)):
        raise CalibrationError(f"{name} must be positive, got {value!r}")
    return float(pair[0]), float(pair[1])


@dataclass(frozen=True)
class CalibrationProblem:
    """The camera's image and what is known about it and about the people seen through it."""

    image_size_px: tuple[float, float]
    height_m: float = DEFAULT_HEIGHT_M
    """Ankle-centre-to-shoulder-centre height prior: sets the metric scale."""
    height_std_m: float = DEFAULT_HEIGHT_STD_M
    """Spread of real heights around height_m."""
    equal_focal: bool = True
    """Square pixels (fx = fy)."""
    principal_point_px: tuple[float, float] | None = None
    """None: the image centre."""
    focal_px: float | tuple[float, float] | None = None
    """A known focal length (one value, or fx and fy): then only the ground plane is solved."""

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
        if self.principal_point_px is not None and not np.all(np.isfinite(self.principal_point_px)):
            raise CalibrationError(f"principal_point_px must be two finite numbers, got {self.principal_point_px!r}")

    @property
    def known_focal_px(self) -> tuple[float, float] | None:
        return None if self.focal_px is None else _positive_pair("focal_px", self.focal_px)


@dataclass(frozen=True)
class SolveOptions:
    """How to solve. The defaults are the most accurate pipeline: RANSAC, then the maximum-likelihood
    refinement with its covariance."""

    robust: bool | None = None
    """RANSAC (None: yes)."""
    refine: bool | None = None
    """The maximum-likelihood refinement (None: yes)."""
    uncertainty: bool = True
    """False skips the covariance (only useful when nothing but the point estimate is wanted, fast)."""
    distortion: bool = False
    """Also estimate one-parameter division-model lens distortion (Appendix B); kept at 0 unless the data call
    for it."""
    seed: int | None = 0
    inlier_px: float | None = None
    """RANSAC's direction threshold; None: 0.3 % of the image diagonal."""
    height_tolerance: float = 0.2
    """RANSAC's relative height threshold."""
    max_iterations: int = 5000
