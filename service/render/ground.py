"""The ground-plane frame that every picture is drawn in, and what part of the ground the camera sees.

Ground coordinates (u, v) in metres are exactly the `ground_m` that `service.frames.measure` stores for each person:
origin at the foot of the camera's perpendicular (-rho N), `v` ("forward") along the camera's viewing direction
projected onto the ground, `u` ("right") = forward x N. (u, v, up) is then right-handed, so a map drawn with u to
the right and v upwards shows the scene as seen from above with the camera at the bottom looking up. Reusing
that definition keeps stored positions, overlays, top-down maps and heat maps in one frame.

The drawings must never put ground above the horizon: ground points in front of the camera always project
below it, but grid lines are infinite and the image rectangle reaches above the horizon. `GroundFrame.visible_polygon`
therefore back-projects the image border clipped to a band below the horizon (and to a range), giving the part
of the ground that can be drawn; clipping lines against it in metres keeps every drawn point on the plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from service.geometry.calibration import Calibration
from service.geometry.camera import Camera, OpenCVLens
from service.geometry.vec import FloatArray

# Camera-frame points closer than this in depth are not projected (a ray at z ~ 0 lands at infinity).
MIN_DEPTH_M = 1e-3


def ground_axes(normal: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """(right, forward) unit vectors on the ground, as `service.frames.measure` defines them.

    forward = the optical axis projected onto the ground; right = forward x N. A camera looking straight down
    has no projected optical axis: then "forward" is the image's up direction (-y) projected instead, so the
    frame is still defined (measuring would produce NaN there; such a camera does not calibrate anyway).
    """
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    forward = np.array([0.0, 0.0, 1.0]) - n[2] * n
    if np.linalg.norm(forward) < 1e-9:
        forward = np.array([0.0, -1.0, 0.0]) - n[1] * n
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, n)
    return right, forward


@dataclass(frozen=True)
class GroundFrame:
    """A calibrated camera (pinhole + division-model distortion) and the ground frame (u, v) on its plane."""

    fx: float
    fy: float
    cx: float
    cy: float
    width_px: int
    height_px: int
    normal: FloatArray
    rho: float
    distortion_k: float = 0.0
    lens: OpenCVLens | None = None  # the user's lens: pictures are drawn through it

    @classmethod
    def from_calibration(cls, cal: Calibration, image_size_px: tuple[int, int] | None = None) -> GroundFrame:
        """The frame of `cal`; with `image_size_px` different from the calibrated size, intrinsics are rescaled.

        Rescaling lets a thumbnail or a downscaled frame be drawn on with the full-size calibration. The
        distortion coefficient works on frame-normalised coordinates, so it is scale-free.
        """
        cal_w, cal_h = float(cal.image_size[0]), float(cal.image_size[1])
        width, height = (cal_w, cal_h) if image_size_px is None else (float(image_size_px[0]), float(image_size_px[1]))
        sx, sy = width / cal_w, height / cal_h
        normal = np.asarray(cal.normal, dtype=np.float64)
        return cls(
            fx=cal.fx * sx,
            fy=cal.fy * sy,
            cx=cal.cx * sx,
            cy=cal.cy * sy,
            width_px=round(width),
            height_px=round(height),
            normal=normal / np.linalg.norm(normal),
            rho=float(cal.rho),
            distortion_k=float(cal.distortion_k),
            lens=cal.lens,  # on focal-normalised coordinates: unchanged by rescaling
        )

    # ------------------------------------------------------------------ frame
    @property
    def origin(self) -> FloatArray:
        """The ground point straight below the camera centre, in the camera frame."""
        return -self.rho * self.normal

    @property
    def axes(self) -> tuple[FloatArray, FloatArray]:
        """(right, forward) unit vectors in the camera frame."""
        return ground_axes(self.normal)

    def ground_to_camera(self, uv: ArrayLike) -> FloatArray:
        """(..., 2) ground metres -> (..., 3) camera-frame points on the plane."""
        p = np.asarray(uv, dtype=np.float64)
        right, forward = self.axes
        return self.origin + p[..., :1] * right + p[..., 1:2] * forward

    def camera_to_ground(self, points: ArrayLike) -> FloatArray:
        """(..., 3) camera-frame points -> (..., 2) ground metres (the orthogonal projection onto the plane)."""
        d = np.asarray(points, dtype=np.float64) - self.origin
        right, forward = self.axes
        return np.stack((d @ right, d @ forward), -1)

    # ------------------------------------------------------------------ pixels
    @property
    def _camera(self) -> Camera:
        size = (float(self.width_px), float(self.height_px))
        return Camera(self.fx, self.fy, self.cx, self.cy, size, self.distortion_k, self.lens)

    def _distort_px(self, ideal_px: FloatArray) -> FloatArray:
        return self._camera.distort_px(ideal_px)

    def _undistort_px(self, px: FloatArray) -> FloatArray:
        return self._camera.undistort_px(px)

    def camera_to_pixels(self, points: ArrayLike) -> FloatArray:
        """(..., 3) camera-frame points -> (..., 2) pixels (with distortion); NaN for points not in front."""
        p = np.asarray(points, dtype=np.float64)
        z = np.where(p[..., 2] > MIN_DEPTH_M, p[..., 2], np.nan)
        ideal = np.stack((self.fx * p[..., 0] / z + self.cx, self.fy * p[..., 1] / z + self.cy), -1)
        return self._distort_px(ideal)

    def ground_to_pixels(self, uv: ArrayLike) -> FloatArray:
        """(..., 2) ground metres -> (..., 2) pixels; NaN for ground behind the camera."""
        return self.camera_to_pixels(self.ground_to_camera(uv))

    def pixel_rays(self, px: ArrayLike) -> FloatArray:
        """(..., 2) pixels -> (..., 3) undistorted viewing rays K^-1 x~ (z = 1)."""
        ideal = self._undistort_px(np.asarray(px, dtype=np.float64))
        return np.stack(
            ((ideal[..., 0] - self.cx) / self.fx, (ideal[..., 1] - self.cy) / self.fy, np.ones(ideal.shape[:-1])), -1
        )

    def pixels_to_camera(self, px: ArrayLike) -> FloatArray:
        """(..., 2) pixels -> (..., 3) where their rays meet the ground; NaN at or above the horizon."""
        ray = self.pixel_rays(px)
        denom = ray @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(denom < 0, -self.rho / denom, np.nan)
        return ray * t[..., None]

    def pixels_to_ground(self, px: ArrayLike) -> FloatArray:
        """(..., 2) pixels -> (..., 2) ground metres; NaN at or above the horizon."""
        return self.camera_to_ground(self.pixels_to_camera(px))

    # ------------------------------------------------------------------ horizon and visibility
    def horizon_line(self) -> FloatArray:
        """The horizon in undistorted pixels as (a, b, c), a x + b y + c = 0 with (a, b) a unit vector.

        Signed distance a x + b y + c is negative below the horizon (where the ground is). All zeros when the
        camera looks straight down (no horizon in the image plane).
        """
        n = self.normal
        line = np.array([n[0] / self.fx, n[1] / self.fy, n[2] - n[0] * self.cx / self.fx - n[1] * self.cy / self.fy])
        norm = float(np.hypot(line[0], line[1]))
        if norm < 1e-15:
            return np.zeros(3)
        return line / norm

    def below_horizon_px(self, px: ArrayLike) -> FloatArray:
        """Signed pixel distance below the horizon of (distorted) pixels: > 0 on the ground side, NaN off-model."""
        ideal = self._undistort_px(np.asarray(px, dtype=np.float64))
        line = self.horizon_line()
        if not np.any(line):
            return np.full(ideal.shape[:-1], np.inf)
        return -(ideal[..., 0] * line[0] + ideal[..., 1] * line[1] + line[2])

    def horizon_y(self, x_px: ArrayLike) -> FloatArray:
        """Row of the (undistorted-model) horizon at each column x; NaN if the horizon is vertical or absent."""
        a, b, c = self.horizon_line()
        x = np.asarray(x_px, dtype=np.float64)
        if abs(b) < 1e-12:
            return np.full(x.shape, np.nan)
        return -(a * x + c) / b

    def visible_polygon(self, *, horizon_margin_px: float = 0.0, max_range_m: float = np.inf) -> FloatArray:
        """(M, 2) ground polygon (metres) of the plane seen inside the image, at least `horizon_margin_px` below
        the horizon and within `max_range_m` of the camera's foot; empty (0, 2) if none of the ground is visible.

        Exact for a pinhole camera (the image rectangle maps to a polygon); with distortion the border is
        sampled densely, so the polygon follows the curved image of the border to within a fraction of a pixel.
        """
        w, h = float(self.width_px), float(self.height_px)
        per_side = 2 if self.distortion_k == 0.0 and self.lens is None else 48
        t = np.linspace(0.0, 1.0, per_side, endpoint=False)
        border = np.concatenate(
            (
                np.stack((t * w, np.zeros_like(t)), -1),
                np.stack((np.full_like(t, w), t * h), -1),
                np.stack(((1 - t) * w, np.full_like(t, h)), -1),
                np.stack((np.zeros_like(t), (1 - t) * h), -1),
            )
        )
        ideal = self._undistort_px(border)
        ideal = ideal[np.all(np.isfinite(ideal), axis=1)]
        line = self.horizon_line()
        if np.any(line):
            ideal = clip_polygon_halfplane(ideal, -line[:2], -line[2] - horizon_margin_px)
        if len(ideal) < 3:
            return np.zeros((0, 2))
        rays = np.stack(((ideal[:, 0] - self.cx) / self.fx, (ideal[:, 1] - self.cy) / self.fy, np.ones(len(ideal))), -1)
        denom = rays @ self.normal
        if np.any(denom >= 0):  # a zero margin exactly on the horizon, or no horizon and no ground in view
            rays = rays[denom < 0]
            denom = denom[denom < 0]
            if len(rays) < 3:
                return np.zeros((0, 2))
        poly = self.camera_to_ground(rays * (-self.rho / denom)[:, None])
        if np.isfinite(max_range_m):
            # A 64-gon around the disc of radius max_range_m: reaches at most 0.12% beyond it.
            for angle in np.linspace(0.0, 2 * np.pi, 64, endpoint=False):
                poly = clip_polygon_halfplane(poly, -np.array([np.cos(angle), np.sin(angle)]), max_range_m)
                if len(poly) < 3:
                    return np.zeros((0, 2))
        return poly


def clip_polygon_halfplane(poly: FloatArray, a: FloatArray, b: float) -> FloatArray:
    """Sutherland-Hodgman: the part of polygon `poly` (M, 2) where a . p + b >= 0."""
    if len(poly) == 0:
        return poly
    s = poly @ a + b
    out: list[FloatArray] = []
    for k in range(len(poly)):
        p, q = poly[k], poly[(k + 1) % len(poly)]
        sp, sq = s[k], s[(k + 1) % len(poly)]
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            out.append(p + (q - p) * (sp / (sp - sq)))
    return np.array(out).reshape(-1, 2)


def clip_line_to_polygon(point: FloatArray, direction: FloatArray, poly: FloatArray) -> list[tuple[float, float]]:
    """Parameter intervals [t0, t1] of the line point + t direction inside polygon `poly` (even-odd rule).

    Works for non-convex polygons (a distorted image border back-projected need not be convex).
    """
    if len(poly) < 3:
        return []
    q0, q1 = poly, np.roll(poly, -1, axis=0)
    e = q1 - q0
    denom = direction[0] * e[:, 1] - direction[1] * e[:, 0]
    rel = q0 - point
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (rel[:, 0] * e[:, 1] - rel[:, 1] * e[:, 0]) / denom
        s = (rel[:, 0] * direction[1] - rel[:, 1] * direction[0]) / denom
    # Half-open on the edge parameter so a line through a vertex counts it once.
    hit = (np.abs(denom) > 1e-15) & (s >= 0) & (s < 1)
    ts = np.sort(t[hit])
    return [(float(ts[k]), float(ts[k + 1])) for k in range(0, len(ts) - 1, 2) if ts[k + 1] > ts[k]]
