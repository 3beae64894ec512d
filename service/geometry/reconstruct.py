"""Metric placement of people from a calibrated camera and ground plane.

People are placed by intersecting the ankle-centre ray with the fitted plane
rather than from their own Eq. 1 depths: those depths assume every person has
the prior height, so their errors never average out when real heights vary.
The shoulder-centre ray then gives each person's own height (closest approach
to the vertical through the ankle), and people whose ankles are hidden are
placed from the shoulder ray against the plane raised by the height prior.
"""

from __future__ import annotations

import numpy as np

from .camera import rays
from .vec import FloatArray, dot


def intersect_plane(ray: FloatArray, normal: FloatArray, offset_m: float | FloatArray) -> FloatArray:
    """Points where rays meet the plane normal . X + offset = 0; NaN rows where a ray misses it.

    A ray misses when it runs parallel to or away from the plane (normal . ray >= 0
    for a plane below the camera): e.g. a foot seen above the horizon.
    """
    denom = dot(ray, normal)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(denom < 0, -np.asarray(offset_m) / denom, np.nan)
    return ray * t[..., None]


def heights_above_ground(points_bottom: FloatArray, ray_top: FloatArray, normal: FloatArray) -> FloatArray:
    """Each person's height (m): where the shoulder ray passes closest to the vertical through the ankle.

    Broadcasts over leading axes, so RANSAC scores a batch of hypotheses with the same definition.
    """
    nr = dot(ray_top, normal)
    rr = dot(ray_top, ray_top)
    nx = dot(points_bottom, normal)
    rx = dot(ray_top, points_bottom)
    # minimise |X_B + t N - s r|^2 over (t, s); |N| = 1.
    det = rr - nr * nr
    with np.errstate(divide="ignore", invalid="ignore"):
        return (-nx * rr + nr * rx) / det


def place_people(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    focal_n: tuple[float, float],
    normal: FloatArray,
    rho_m: float,
    height_m: float,
    ankles_visible: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(points_bottom, points_top, heights) in camera-frame metres; NaN where a person cannot be placed."""
    ray_b = rays(bottoms_n, focal_n)
    ray_t = rays(tops_n, focal_n)
    x_b = intersect_plane(ray_b, normal, rho_m)
    heights = heights_above_ground(x_b, ray_t, normal)
    if ankles_visible is not None and not np.all(ankles_visible):
        hidden = ~np.asarray(ankles_visible, dtype=bool)
        x_t_hidden = intersect_plane(ray_t[hidden], normal, rho_m - height_m)
        x_b[hidden] = x_t_hidden - height_m * normal
        heights[hidden] = height_m
    x_t = x_b + heights[:, None] * normal
    return x_b, x_t, heights
