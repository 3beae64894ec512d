"""The ground grid: lines u = k c and v = k c (c the cell size) clipped to the part of the ground in view.

Lines are clipped in ground metres against `GroundFrame.visible_polygon` and only then projected, so every
drawn point is a projection of a point on the plane (never of the plane's far side behind the camera, which
would land above the horizon) and distortion bends the lines exactly as it bends the ground.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.domain import METRES_PER_FOOT
from service.geometry.vec import FloatArray

from .ground import GroundFrame, clip_line_to_polygon

SIX_FEET_M = 6 * METRES_PER_FOOT
# Default reach of the grid, in cells: beyond about 40 cells a 1 m grid is a grey smear near the horizon.
DEFAULT_RANGE_CELLS = 40


@dataclass(frozen=True)
class GridSegment:
    """One visible piece of a grid line: ground samples (metres), their pixels, their range from the camera foot."""

    axis: int  # 0: a line of constant u; 1: constant v
    index: int  # the line is axis-coordinate = index * cell
    ground_m: FloatArray  # (S, 2)
    pixels: FloatArray  # (S, 2)
    range_m: FloatArray  # (S,) distance of each sample from the camera's foot on the ground


def default_horizon_margin_px(frame: GroundFrame, cell_m: float = 1.0, min_spacing_px: float | None = None) -> float:
    """How far below the horizon the grid stops: where successive lines come closer than `min_spacing_px`.

    A ground point at depth z lies delta = rho / (z |grad g|) pixels below the horizon (g = N . K^-1 x~, the
    horizon's defining function), so one cell further away (depth + c f_z, f_z the forward axis's depth
    component) moves it by about delta^2 |grad g| c f_z / rho pixels; solving for the given spacing gives the
    margin. Beyond it the grid is a smear that hides the picture. The spacing defaults to 0.8% of the image
    height (at least 5 px); the margin is at least 3% of the image height, and 4 px.
    """
    spacing = max(5.0, 0.008 * frame.height_px) if min_spacing_px is None else min_spacing_px
    line = frame.horizon_line()
    floor = max(4.0, 0.03 * frame.height_px)
    if not np.any(line):
        return floor
    n = frame.normal
    grad = float(np.hypot(n[0] / frame.fx, n[1] / frame.fy))
    depth_step = cell_m * max(float(frame.axes[1][2]), 1e-3)
    return max(floor, float(np.sqrt(spacing * frame.rho / (grad * depth_step))))


def grid_segments(
    frame: GroundFrame,
    cell_m: float = 1.0,
    *,
    max_range_m: float | None = None,
    horizon_margin_px: float | None = None,
    max_step_m: float | None = None,
) -> list[GridSegment]:
    """Every visible piece of the grid, sampled at most `max_step_m` apart (default: half a cell).

    Sampling matters only under lens distortion (lines bend) and for fading (alpha varies along a line); the
    first and last samples are the exact clip points.
    """
    if not cell_m > 0:
        raise ValueError(f"grid cell must be positive, got {cell_m!r}")
    reach = DEFAULT_RANGE_CELLS * cell_m if max_range_m is None else max_range_m
    margin = default_horizon_margin_px(frame, cell_m) if horizon_margin_px is None else horizon_margin_px
    step = cell_m / 2 if max_step_m is None else max_step_m
    poly = frame.visible_polygon(horizon_margin_px=margin, max_range_m=reach)
    if len(poly) < 3:
        return []
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    segments: list[GridSegment] = []
    for axis in (0, 1):
        direction = np.array([0.0, 1.0]) if axis == 0 else np.array([1.0, 0.0])
        for k in range(int(np.ceil(lo[axis] / cell_m)), int(np.floor(hi[axis] / cell_m)) + 1):
            point = np.zeros(2)
            point[axis] = k * cell_m
            for t0, t1 in clip_line_to_polygon(point, direction, poly):
                n = int(min(max(np.ceil((t1 - t0) / step), 1), 400)) + 1
                ground = point + np.linspace(t0, t1, n)[:, None] * direction
                pixels = frame.ground_to_pixels(ground)
                keep = np.all(np.isfinite(pixels), axis=1)
                if np.count_nonzero(keep) < 2:
                    continue
                ground, pixels = ground[keep], pixels[keep]
                segments.append(GridSegment(axis, k, ground, pixels, np.hypot(ground[:, 0], ground[:, 1])))
    return segments
