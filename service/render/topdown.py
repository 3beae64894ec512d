"""A map of the scene from above: people at their ground positions, the camera and what it sees, close pairs.

Distances that look wrong in perspective (a pair far away seems close) read correctly on a map with equal
aspect and a scale bar; the map uses the stored ground frame (u right, v forward, camera foot at the origin),
so u runs to the right and v upwards, with the camera at the bottom looking up the image.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike

from service.geometry.calibration import Calibration
from service.geometry.vec import FloatArray

from .ground import GroundFrame
from .overlay import PairLike, PersonMark, violators
from .style import GREEN, LIGHT_RED, RED, SHIFT, WHITE, Style, fixed, format_distance, label, line, text_height

BACKGROUND = (38, 34, 30)
GRID = (70, 66, 62)
GRID_MAJOR = (95, 90, 85)
FOV_FILL = (90, 70, 40)
FOV_EDGE = (200, 160, 90)


@dataclass(frozen=True)
class TopDownView:
    """Ground metres <-> map pixels: `centre_m` at the image centre, `metres_per_px` on both axes, v up."""

    width_px: int
    height_px: int
    centre_m: tuple[float, float]
    metres_per_px: float

    def to_pixels(self, uv: ArrayLike) -> FloatArray:
        """(..., 2) ground metres -> (..., 2) map pixels (float, pixel centres at integers)."""
        p = np.asarray(uv, dtype=np.float64)
        x = (self.width_px - 1) / 2 + (p[..., 0] - self.centre_m[0]) / self.metres_per_px
        y = (self.height_px - 1) / 2 - (p[..., 1] - self.centre_m[1]) / self.metres_per_px
        return np.stack((x, y), -1)

    def to_ground(self, px: ArrayLike) -> FloatArray:
        """(..., 2) map pixels -> (..., 2) ground metres."""
        p = np.asarray(px, dtype=np.float64)
        u = self.centre_m[0] + (p[..., 0] - (self.width_px - 1) / 2) * self.metres_per_px
        v = self.centre_m[1] - (p[..., 1] - (self.height_px - 1) / 2) * self.metres_per_px
        return np.stack((u, v), -1)

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(u_min, u_max, v_min, v_max) covered by the map."""
        (u0, v1), (u1, v0) = self.to_ground(np.array([[-0.5, -0.5], [self.width_px - 0.5, self.height_px - 0.5]]))
        return float(u0), float(u1), float(v0), float(v1)


def _size(size_px: int | tuple[int, int]) -> tuple[int, int]:
    w, h = (size_px, size_px) if isinstance(size_px, int) else size_px
    if w < 1 or h < 1:
        raise ValueError(f"map size must be positive, got {size_px!r}")
    return int(w), int(h)


def fit_view(
    points_m: ArrayLike,
    size_px: int | tuple[int, int] = 800,
    *,
    margin_m: float = 1.5,
    min_span_m: float = 6.0,
) -> TopDownView:
    """The view that shows every finite point with `margin_m` around it, at equal aspect, at least `min_span_m` wide."""
    w, h = _size(size_px)
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 2)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) == 0:
        p = np.zeros((1, 2))
    lo, hi = p.min(axis=0) - margin_m, p.max(axis=0) + margin_m
    span = np.maximum(hi - lo, min_span_m)
    mpp = float(max(span[0] / w, span[1] / h))
    centre = (lo + hi) / 2
    return TopDownView(w, h, (float(centre[0]), float(centre[1])), mpp)


def nice_step(target: float) -> float:
    """The 1-2-5 number closest below `target` (a scale bar or grid step that reads well)."""
    if not target > 0:
        return 1.0
    base = 10 ** math.floor(math.log10(target))
    return max(m * base for m in (1, 2, 5) if m * base <= target)


def draw_ground_grid(image: np.ndarray, view: TopDownView, style: Style, grid_m: float = 1.0) -> None:
    """Lines u, v = k grid_m (in place); every fifth line brighter; thinned out when cells get under 6 px."""
    step = grid_m
    while step / view.metres_per_px < 6:
        step *= 5
    u0, u1, v0, v1 = view.extent_m
    for axis, (a0, a1) in enumerate(((u0, u1), (v0, v1))):
        for k in range(math.ceil(a0 / step), math.floor(a1 / step) + 1):
            value = k * step
            ends = np.array([[value, v0], [value, v1]]) if axis == 0 else np.array([[u0, value], [u1, value]])
            px = view.to_pixels(ends)
            major = k % 5 == 0
            line(image, px[0], px[1], GRID_MAJOR if major else GRID, style.thin_px)


def draw_scale_bar(image: np.ndarray, view: TopDownView, style: Style) -> None:
    """A 1-2-5 metre bar about a fifth of the map wide, bottom left, labelled."""
    length_m = nice_step(view.width_px * view.metres_per_px / 5)
    length_px = length_m / view.metres_per_px
    x0 = 2 * style.pad_px + 4
    y = view.height_px - 2 * style.pad_px - 4
    tick = 2 * style.marker_px
    pts = np.array([[x0, y - tick], [x0, y], [x0 + length_px, y], [x0 + length_px, y - tick]])
    cv2.polylines(image, [fixed(pts).reshape(-1, 1, 2)], False, WHITE, style.line_px, cv2.LINE_AA, SHIFT)
    text = f"{length_m:g} m"
    label(image, text, (x0 + length_px + style.pad_px, y + style.pad_px), style, align="bottomleft")


def fov_edges(poly: FloatArray) -> list[FloatArray]:
    """The two vertices of the visible-ground polygon at the extreme bearings seen from the origin (camera foot).

    Empty when the polygon surrounds the origin (a camera looking nearly straight down sees all around its foot).
    """
    if len(poly) < 3:
        return []
    angles = np.arctan2(poly[:, 0], poly[:, 1])  # bearing from forward (+v), positive to the right
    centre = np.arctan2(*poly.mean(axis=0))
    rel = (angles - centre + np.pi) % (2 * np.pi) - np.pi
    if rel.max() - rel.min() >= np.pi:
        return []
    return [poly[int(np.argmin(rel))], poly[int(np.argmax(rel))]]


def draw_camera(image: np.ndarray, view: TopDownView, style: Style, calibration: Calibration) -> None:
    """The ground the camera sees (filled, translucent) and the camera's foot as a marker at the origin."""
    frame = GroundFrame.from_calibration(calibration)
    u0, u1, v0, v1 = view.extent_m
    reach = 2.0 * math.hypot(max(abs(u0), abs(u1)), max(abs(v0), abs(v1)))
    poly = frame.visible_polygon(max_range_m=reach)
    if len(poly) >= 3:
        layer = image.copy()
        pts = fixed(view.to_pixels(poly)).reshape(-1, 1, 2)
        cv2.fillPoly(layer, [pts], FOV_FILL, cv2.LINE_AA, SHIFT)
        cv2.addWeighted(layer, 0.35, image, 0.65, 0.0, dst=image)
        cv2.polylines(image, [pts], True, FOV_EDGE, style.thin_px, cv2.LINE_AA, SHIFT)
        # The wedge: bearings from the camera's foot that bound everything it sees.
        for corner in fov_edges(poly):
            far = corner / np.linalg.norm(corner) * reach
            line(image, view.to_pixels(np.zeros(2)), view.to_pixels(far), FOV_EDGE, style.thin_px)
    # The camera: a triangle at its foot, pointing forward (+v, up the map).
    c = view.to_pixels(np.zeros(2))
    r = 1.6 * style.marker_px
    tri = np.array([[c[0], c[1] - r], [c[0] - 0.8 * r, c[1] + 0.7 * r], [c[0] + 0.8 * r, c[1] + 0.7 * r]])
    cv2.fillPoly(image, [fixed(tri).reshape(-1, 1, 2)], WHITE, cv2.LINE_AA, SHIFT)


def render_topdown(
    people: Sequence[PersonMark],
    pairs: Sequence[PairLike],
    threshold_m: float,
    *,
    size_px: int | tuple[int, int] = 800,
    calibration: Calibration | None = None,
    view: TopDownView | None = None,
    grid_m: float = 1.0,
    threshold_circles: bool = True,
    unit: str = "m",
) -> np.ndarray:
    """The map as a BGR image: grid and scale bar, camera and its view (given a calibration), people as dots
    (red when in a pair under the threshold), those pairs as labelled red lines, and optionally a circle of
    radius threshold/2 around each person (two circles overlap exactly when the pair is under the threshold).

    `view` fixes the mapping (e.g. to keep successive frames aligned); by default it fits the people and,
    with a calibration, the camera's foot.
    """
    placed = {p.index: np.array(p.ground_m, dtype=float) for p in people if p.ground_m is not None}
    placed = {i: g for i, g in placed.items() if np.all(np.isfinite(g))}
    if view is None:
        points = list(placed.values()) + ([np.zeros(2)] if calibration is not None else [])
        view = fit_view(np.array(points).reshape(-1, 2), size_px)
    image = np.empty((view.height_px, view.width_px, 3), dtype=np.uint8)
    image[...] = BACKGROUND
    style = Style.for_size(view.width_px, view.height_px)
    draw_ground_grid(image, view, style, grid_m)
    if calibration is not None:
        draw_camera(image, view, style, calibration)

    red = violators(pairs, threshold_m)
    if threshold_circles:
        radius_px = threshold_m / 2 / view.metres_per_px
        for i, g in placed.items():
            c = view.to_pixels(g)
            cv2.circle(
                image, _pt(c), int(np.rint(radius_px * (1 << SHIFT))), RED if i in red else GREEN, 1, cv2.LINE_AA, SHIFT
            )
    close = [
        p for p in pairs if p.distance_m is not None and p.distance_m < threshold_m and p.i in placed and p.j in placed
    ]
    for p in close:
        line(image, view.to_pixels(placed[p.i]), view.to_pixels(placed[p.j]), RED, style.line_px)
    for p in close:
        # Above the pair's midpoint rather than on it: two close people's dots would hide under their own label.
        mid = view.to_pixels((placed[p.i] + placed[p.j]) / 2) - (0.0, text_height(style) / 2 + 1.5 * style.marker_px)
        label(image, format_distance(p.distance_m, unit), (float(mid[0]), float(mid[1])), style, color=LIGHT_RED)  # type: ignore[arg-type]
    # Dots last: a label may overlap a neighbour's dot, never hide it.
    for i, g in placed.items():
        cv2.circle(
            image, _pt(view.to_pixels(g)), style.marker_px << SHIFT, RED if i in red else GREEN, -1, cv2.LINE_AA, SHIFT
        )
    draw_scale_bar(image, view, style)
    return image


def _pt(p: FloatArray) -> tuple[int, int]:
    q = fixed(p)
    return int(q[0]), int(q[1])
