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
class OpenCVLens:
    """OpenCV's lens model on focal-normalised coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy):

        x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
        y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

    the coefficients real calibrations publish (cv2.calibrateCamera's first five).
    """

    k1: float
    k2: float
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @classmethod
    def from_coefficients(cls, coefficients: ArrayLike) -> OpenCVLens:
        c = [float(v) for v in np.asarray(coefficients, dtype=np.float64).ravel()]
        if len(c) not in (4, 5) or not all(np.isfinite(c)):
            raise ValueError(f"OpenCV distortion needs 4 or 5 finite coefficients (k1, k2, p1, p2[, k3]), got {c}")
        return cls(*c)

    @property
    def coefficients(self) -> tuple[float, float, float, float, float]:
        return (self.k1, self.k2, self.p1, self.p2, self.k3)

    def distort(self, xy: FloatArray) -> FloatArray:
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack((xd, yd), -1)

    def undistort(self, xy_d: FloatArray, iterations: int = 30) -> FloatArray:
        """Inverse of distort by Newton's method (the model has no closed-form inverse); NaN where it does not
        converge (beyond the lens's monotone range)."""
        xy_d = np.asarray(xy_d, dtype=np.float64)
        xy = xy_d.copy()
        for _ in range(iterations):
            x, y = xy[..., 0], xy[..., 1]
            r2 = x * x + y * y
            radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
            d_radial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3)  # d radial / d r2
            err = self.distort(xy) - xy_d
            j00 = radial + 2.0 * x * x * d_radial + 2.0 * self.p1 * y + 6.0 * self.p2 * x
            j01 = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y
            j10 = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y
            j11 = radial + 2.0 * y * y * d_radial + 6.0 * self.p1 * y + 2.0 * self.p2 * x
            det = j00 * j11 - j01 * j10
            with np.errstate(divide="ignore", invalid="ignore"):
                dx = (j11 * err[..., 0] - j01 * err[..., 1]) / det
                dy = (j00 * err[..., 1] - j10 * err[..., 0]) / det
            xy = xy - np.stack((dx, dy), -1)
        ok = np.all(np.abs(self.distort(xy) - xy_d) < 1e-9 * np.maximum(1.0, np.abs(xy_d)), axis=-1)
        return np.where(ok[..., None], xy, np.nan)


@dataclass(frozen=True)
class Camera:
    """A calibrated camera's intrinsics and lens: what turns pixels into rays and camera-frame points into pixels.

    The lens is OpenCV's model when the user gave its coefficients, or the division model when the
    calibration estimated one (distortion_k, frame-normalised about the principal point); never both.
    """

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    image_size_px: tuple[float, float]
    distortion_k: float = 0.0
    lens: OpenCVLens | None = None

    @property
    def frame(self) -> ImageFrame:
        return ImageFrame.from_size(self.image_size_px, (self.cx_px, self.cy_px))

    def _focal_normalised(self, points_px: FloatArray) -> FloatArray:
        p = np.asarray(points_px, dtype=np.float64)
        return np.stack(((p[..., 0] - self.cx_px) / self.fx_px, (p[..., 1] - self.cy_px) / self.fy_px), -1)

    def _from_focal_normalised(self, xy: FloatArray) -> FloatArray:
        return np.stack((xy[..., 0] * self.fx_px + self.cx_px, xy[..., 1] * self.fy_px + self.cy_px), -1)

    def undistort_px(self, points_px: FloatArray) -> FloatArray:
        """Measured -> ideal pinhole pixels (identity without distortion)."""
        if self.lens is not None:
            return self._from_focal_normalised(self.lens.undistort(self._focal_normalised(points_px)))
        if self.distortion_k == 0.0:
            return points_px
        frame = self.frame
        return frame.to_pixels(undistort(frame.normalise(points_px), self.distortion_k))

    def distort_px(self, ideal_px: FloatArray) -> FloatArray:
        """Ideal pinhole pixels -> where the lens puts them (identity without distortion)."""
        if self.lens is not None:
            return self._from_focal_normalised(self.lens.distort(self._focal_normalised(ideal_px)))
        if self.distortion_k == 0.0:
            return ideal_px
        frame = self.frame
        return frame.to_pixels(distort(frame.normalise(ideal_px), self.distortion_k))

    def project(self, points: FloatArray) -> FloatArray:
        """Camera-frame points -> pixels, through the lens."""
        z = points[..., 2]
        ideal = np.stack(
            (self.fx_px * points[..., 0] / z + self.cx_px, self.fy_px * points[..., 1] / z + self.cy_px), -1
        )
        return self.distort_px(ideal)

    def rays(self, points_px: FloatArray) -> FloatArray:
        """Pixels -> viewing rays K^-1 x~ (z = 1) of their undistorted positions."""
        ideal = self.undistort_px(points_px)
        return rays(ideal - np.array([self.cx_px, self.cy_px]), np.array([self.fx_px, self.fy_px]))
