"""The camera model in one place: principal point, focal lengths, lens distortion, rays and projection.

Pixels have their origin at the top-left corner, x right, y down; the camera frame is x right, y down,
z forward. A pinhole camera K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] maps a camera-frame point X to the
ideal (undistorted) pixel K X / Z; a lens then moves ideal pixels radially about the principal point.

Two coordinate systems serve the solvers:

* frame-normalised coordinates u = (x - c) / s with s = (W + H) / 4 (`ImageFrame`). The linear equations
  mix pixel-sized terms (x, y ~ 10^3) with the homogeneous 1; in raw pixels the third row of Eq. 1 is
  swamped and the solution loses several digits. The scale comes from the image size alone (not from the
  points), so scaling an image and its points by s leaves the normalised problem unchanged and f scales
  exactly by s. Focal lengths inside the solvers are in these units (focal_n = f_px / s).
* focal-normalised coordinates (x - cx) / fx, (y - cy) / fy: viewing rays with z = 1 (`rays`).

The one-parameter division model of lens distortion (Fitzgibbon 2001; the paper's Appendix B) lives on
frame-normalised coordinates: the undistorted point is u = u_d / (1 + k |u_d|^2). Working in normalised
rather than pixel units keeps k of order 0.1 for real lenses instead of 1e-7. `project` also offers the
OpenCV polynomial radial model on focal-normalised coordinates, the model real calibrations publish.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .vec import FloatArray


@dataclass(frozen=True)
class ImageFrame:
    """Principal point (pixels) and the conditioning scale (pixels per frame-normalised unit)."""

    width_px: float
    height_px: float
    cx_px: float
    cy_px: float
    scale_px: float

    @classmethod
    def from_size(
        cls,
        image_size: tuple[float, float],
        principal_point: tuple[float, float] | None = None,
    ) -> ImageFrame:
        width, height = (float(image_size[0]), float(image_size[1]))
        if not (np.isfinite(width) and np.isfinite(height) and width > 0 and height > 0):
            raise ValueError(f"image_size must be two positive numbers, got {image_size!r}")
        cx, cy = (width / 2.0, height / 2.0) if principal_point is None else principal_point
        # Half the mean side: maps a typical image onto roughly [-1.3, 1.3] x [-0.8, 0.8].
        return cls(width, height, float(cx), float(cy), (width + height) / 4.0)

    @property
    def diagonal_px(self) -> float:
        return float(np.hypot(self.width_px, self.height_px))

    def normalise(self, points_px: ArrayLike) -> FloatArray:
        p = np.asarray(points_px, dtype=np.float64)
        return np.stack(((p[..., 0] - self.cx_px) / self.scale_px, (p[..., 1] - self.cy_px) / self.scale_px), -1)

    def to_pixels(self, points_n: ArrayLike) -> FloatArray:
        p = np.asarray(points_n, dtype=np.float64)
        return np.stack((p[..., 0] * self.scale_px + self.cx_px, p[..., 1] * self.scale_px + self.cy_px), -1)


# --- the division model of lens distortion (frame-normalised coordinates) --------------------------------------


def undistort(points_n: ArrayLike, k: float) -> FloatArray:
    """Distorted -> undistorted normalised points; NaN where 1 + k r^2 <= 0 (beyond the model's horizon)."""
    p = np.asarray(points_n, dtype=np.float64)
    denom = 1.0 + k * np.sum(p * p, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((denom > 0)[..., None], p / denom[..., None], np.nan)


def distort(points_n: ArrayLike, k: float) -> FloatArray:
    """Undistorted -> distorted normalised points (inverse of undistort); NaN where no real preimage exists.

    r_d solves k r_u r_d^2 - r_d + r_u = 0; of its two roots only the one
    continuous at k = 0 lies on the monotone branch (k r_d^2 < 1), and it is
    written as 2 r_u / (1 + sqrt(1 - 4 k r_u^2)) to stay exact for k -> 0 and
    r_u -> 0. For k > 0 points beyond r_u = 1 / (2 sqrt(k)) have no preimage.
    """
    p = np.asarray(points_n, dtype=np.float64)
    disc = 1.0 - 4.0 * k * np.sum(p * p, -1)
    with np.errstate(invalid="ignore"):
        factor = np.where(disc >= 0, 2.0 / (1.0 + np.sqrt(np.maximum(disc, 0.0))), np.nan)
    return p * factor[..., None]


def lifted(points_n: FloatArray, k: float | FloatArray) -> FloatArray:
    """Homogeneous undistorted points (u_d, 1 + k r_d^2), (..., N, 3); k broadcasts as (...,)."""
    kk = np.asarray(k, dtype=np.float64)[..., None]
    w = 1.0 + kk * np.sum(points_n * points_n, -1)
    return np.concatenate((np.broadcast_to(points_n, w.shape + (2,)), w[..., None]), -1)


# --- rays and projection -------------------------------------------------------------------------------------------


def rays(points_n: FloatArray, focal_n: ArrayLike) -> FloatArray:
    """K^-1 x~ for points centred on the principal point: viewing rays (z = 1), (..., 3).

    focal_n (..., 2) is in the points' units and broadcasts against them, so one call
    serves one camera or a batch of hypotheses.
    """
    f = np.asarray(focal_n, dtype=np.float64)
    x, y = points_n[..., 0] / f[..., 0], points_n[..., 1] / f[..., 1]
    return np.stack((x, y, np.ones_like(x)), -1)


def project(
    points: FloatArray, fx: float, fy: float, cx: float, cy: float, k: tuple[float, float] = (0.0, 0.0)
) -> FloatArray:
    """Pinhole projection of camera-frame points to pixels, with OpenCV polynomial radial distortion
    (k1, k2 on focal-normalised coordinates) when k != 0."""
    xn = points[..., 0] / points[..., 2]
    yn = points[..., 1] / points[..., 2]
    if k != (0.0, 0.0):
        r2 = xn * xn + yn * yn
        factor = 1.0 + k[0] * r2 + k[1] * r2 * r2
        xn, yn = xn * factor, yn * factor
    return np.stack((fx * xn + cx, fy * yn + cy), -1)


@dataclass(frozen=True)
class Camera:
    """A calibrated camera's intrinsics and lens: what turns pixels into rays and camera-frame points into pixels."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    image_size_px: tuple[float, float]
    # Division model on frame-normalised coordinates (see the module docstring).
    distortion_k: float = 0.0

    @property
    def frame(self) -> ImageFrame:
        return ImageFrame.from_size(self.image_size_px, (self.cx_px, self.cy_px))

    def undistort_px(self, points_px: FloatArray) -> FloatArray:
        """Measured -> ideal pinhole pixels (identity without distortion)."""
        if self.distortion_k == 0.0:
            return points_px
        frame = self.frame
        return frame.to_pixels(undistort(frame.normalise(points_px), self.distortion_k))

    def distort_px(self, ideal_px: FloatArray) -> FloatArray:
        """Ideal pinhole pixels -> where the lens puts them (identity without distortion)."""
        if self.distortion_k == 0.0:
            return ideal_px
        frame = self.frame
        return frame.to_pixels(distort(frame.normalise(ideal_px), self.distortion_k))
