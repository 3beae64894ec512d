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
from .labels import Box, box_at, place_labels
from .overlay import PairLike, PersonMark, violators
from .style import (
    GREEN,
    LIGHT_RED,
    RED,
    SHIFT,
    WHITE,
    Style,
    fixed,
    format_distance,
    label,
    label_size,
    line,
    text_height,
)

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


def scale_bar_box(view: TopDownView, style: Style) -> Box:
    """The box the scale bar and its label cover (draw_scale_bar draws exactly this)."""
    length_m, length_px, x0, y, tick = _scale_bar(view, style)
    w, h = label_size(f"{length_m:g} m", style)
    right = round(x0 + length_px + style.pad_px) + w
    return Box(0, round(min(y + style.pad_px - h, y - tick)) - style.pad_px, right + style.pad_px, view.height_px - 1)


def _scale_bar(view: TopDownView, style: Style) -> tuple[float, float, int, int, int]:
    length_m = nice_step(view.width_px * view.metres_per_px / 5)
    return (
        length_m,
        length_m / view.metres_per_px,
        2 * style.pad_px + 4,
        view.height_px - 2 * style.pad_px - 4,
        2 * style.marker_px,
    )


def draw_scale_bar(image: np.ndarray, view: TopDownView, style: Style) -> None:
    """A 1-2-5 metre bar about a fifth of the map wide, bottom left, labelled."""
    length_m, length_px, x0, y, tick = _scale_bar(view, style)
    pts = np.array([[x0, y - tick], [x0, y], [x0 + length_px, y], [x0 + length_px, y - tick]])
    cv2.polylines(image, [fixed(pts).reshape(-1, 1, 2)], False, WHITE, style.line_px, cv2.LINE_AA, SHIFT)
    label(image, f"{length_m:g} m", (x0 + length_px + style.pad_px, y + style.pad_px), style, align="bottomleft")


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
    title: str | None = None,
) -> np.ndarray:
    """The map as a BGR image: grid and scale bar, camera and its view (given a calibration), people as dots
    (red when in a pair under the threshold), those pairs as red lines labelled with their distance, and
    optionally a circle of radius threshold/2 around each person (two circles overlap exactly when the pair is
    under the threshold). `title` (camera, time) heads the map, with a note of what it could not show.

    `view` fixes the mapping (e.g. to keep successive frames aligned); by default it fits the people and,
    with a calibration, the camera's foot. People outside the view are drawn as arrows at the edge, pointing to
    where they stand. Distance labels never overlap each other or the title and scale bar (service.render.labels):
    the closest pairs are labelled first, and a label with no free spot is left out and counted in the note.
    """
    if view is None:
        grounds = [p.ground_m for p in people if p.ground_m is not None and np.all(np.isfinite(p.ground_m))]
        points = list(grounds) + ([(0.0, 0.0)] if calibration is not None else [])
        view = fit_view(np.array(points, dtype=float).reshape(-1, 2), size_px)
    image = np.empty((view.height_px, view.width_px, 3), dtype=np.uint8)
    image[...] = BACKGROUND
    style = Style.for_size(view.width_px, view.height_px)
    draw_ground_grid(image, view, style, grid_m)
    if calibration is not None:
        draw_camera(image, view, style, calibration)

    layout = topdown_layout(people, pairs, threshold_m, view, style, unit)
    red = violators(pairs, threshold_m)
    colour = {i: RED if i in red else GREEN for i in layout.pixels}
    if threshold_circles:
        radius = int(np.rint(threshold_m / 2 / view.metres_per_px * (1 << SHIFT)))
        for i in layout.on_map:
            cv2.circle(image, _pt(layout.pixels[i]), radius, colour[i], 1, cv2.LINE_AA, SHIFT)
    for p in layout.close:
        line(image, layout.pixels[p.i], layout.pixels[p.j], RED, style.line_px)
    draw_scale_bar(image, view, style)
    _draw_distance_labels(image, style, layout.labels)
    # Dots last: labels keep clear of them, so nothing hides a person.
    for i in layout.on_map:
        cv2.circle(image, _pt(layout.pixels[i]), style.marker_px << SHIFT, colour[i], -1, cv2.LINE_AA, SHIFT)
    for i in layout.off_map:
        _edge_arrow(image, layout.area, layout.pixels[i], style, colour[i])
    if title:
        label(image, title, (0, 0), style, align="topleft")
    hidden = sum(found.box is None for found in layout.labels)
    notes = [f"{len(layout.off_map)} off map"] if layout.off_map else []
    if hidden:
        notes.append(f"{hidden} label{'s' * (hidden != 1)} hidden: crowded")
    if notes:
        label(image, ", ".join(notes), (view.width_px, view.height_px), style, align="bottomright")
    return image


@dataclass(frozen=True)
class TopDownLayout:
    """Where everything of a map goes, before anything is drawn."""

    pixels: dict[int, FloatArray]
    """Each placed person's map pixel (off-map people's lie outside `area`)."""
    area: Box
    """Where people are drawn: the map less an inset at the edges and the title line."""
    on_map: list[int]
    off_map: list[int]
    close: list[PairLike]
    """The pairs under the threshold with both people placed, closest first."""
    reserved: list[Box]
    """What labels keep clear of: the title line, the note line, the scale bar, every on-map person's dot."""
    labels: list[DistanceLabel]


def topdown_layout(
    people: Sequence[PersonMark],
    pairs: Sequence[PairLike],
    threshold_m: float,
    view: TopDownView,
    style: Style,
    unit: str = "m",
) -> TopDownLayout:
    placed = {p.index: np.array(p.ground_m, dtype=float) for p in people if p.ground_m is not None}
    pixels = {i: view.to_pixels(g) for i, g in placed.items() if np.all(np.isfinite(g))}
    inset = 2 * style.marker_px + style.pad_px
    title_band = _title_band(view, style)
    area = Box(inset, title_band.y1 + inset, view.width_px - 1 - inset, view.height_px - 1 - inset)
    on_map = sorted(i for i, c in pixels.items() if area.x0 <= c[0] <= area.x1 and area.y0 <= c[1] <= area.y1)
    close = [p for p in pairs if p.distance_m is not None and p.distance_m < threshold_m]
    close = sorted((p for p in close if p.i in pixels and p.j in pixels), key=lambda p: float(p.distance_m or 0.0))
    dots = [box_at((float(pixels[i][0]), float(pixels[i][1])), (2 * style.marker_px + 1,) * 2) for i in on_map]
    reserved = [title_band, _note_band(view, style), scale_bar_box(view, style), *dots]
    labels = distance_labels(view, style, close, pixels, reserved, unit)
    off_map = sorted(set(pixels) - set(on_map))
    return TopDownLayout(pixels, area, on_map, off_map, close, reserved, labels)


def _title_band(view: TopDownView, style: Style) -> Box:
    """The top line, kept free for the title (camera, time)."""
    return Box(0, 0, view.width_px - 1, text_height(style))


def _note_band(view: TopDownView, style: Style) -> Box:
    """The bottom line right of the scale bar, kept free for the note of what the map leaves out (known only once
    the labels are placed)."""
    return Box(view.width_px // 3, view.height_px - 1 - text_height(style), view.width_px - 1, view.height_px - 1)


@dataclass(frozen=True)
class DistanceLabel:
    """A close pair's label: its text, the point of the pair's line it belongs to, and its box (None: left out)."""

    text: str
    anchor_px: tuple[float, float]
    box: Box | None


def distance_labels(
    view: TopDownView,
    style: Style,
    close: Sequence[PairLike],
    pixels: dict[int, FloatArray],
    reserved: Sequence[Box],
    unit: str = "m",
) -> list[DistanceLabel]:
    """Where the close pairs' labels go (closest pair first), by labels.place_labels: above the visible part of the
    pair's line (two close people's dots would hide under a label on the midpoint) or, when crowded, nearby (drawn
    with a thin leader line); never over each other or a `reserved` box."""
    texts = [format_distance(float(p.distance_m or 0.0), unit) for p in close]
    anchors = []
    for p in close:
        a, b = _clipped(pixels[p.i], pixels[p.j], view)
        anchors.append((float(a[0] + b[0]) / 2, float(a[1] + b[1]) / 2))
    lift = text_height(style) / 2 + 1.5 * style.marker_px
    bounds = Box(0, 0, view.width_px - 1, view.height_px - 1)
    sizes = [label_size(text, style) for text in texts]
    boxes = place_labels(sizes, [(x, y - lift) for x, y in anchors], bounds, reserved)
    return [DistanceLabel(*found) for found in zip(texts, anchors, boxes, strict=True)]


def _draw_distance_labels(image: np.ndarray, style: Style, labels: Sequence[DistanceLabel]) -> None:
    lift = text_height(style) / 2 + 1.5 * style.marker_px
    for found in labels:
        if found.box is not None and math.dist(found.box.centre, (found.anchor_px[0], found.anchor_px[1] - lift)) > 1:
            line(image, np.array(found.anchor_px), np.array(found.box.centre), LIGHT_RED, 1)
    for found in labels:
        if found.box is not None:
            label(image, found.text, (found.box.x0, found.box.y0), style, color=LIGHT_RED, align="topleft")


def _clipped(a: FloatArray, b: FloatArray, view: TopDownView) -> tuple[FloatArray, FloatArray]:
    """The part of segment ab inside the map (the whole segment when it is all inside, or none is)."""
    inside, p, q = cv2.clipLine((0, 0, view.width_px, view.height_px), _int(a), _int(b))
    return (np.array(p, float), np.array(q, float)) if inside else (a, b)


def _int(p: FloatArray) -> tuple[int, int]:
    q = np.clip(np.rint(p), -(1 << 20), 1 << 20)
    return int(q[0]), int(q[1])


def _edge_arrow(image: np.ndarray, area: Box, target: FloatArray, style: Style, colour: tuple[int, int, int]) -> None:
    """An arrowhead on the edge of the map's area, on the line from its centre towards a person beyond it."""
    centre = np.array(area.centre)
    direction = target - centre
    half = np.array([(area.x1 - area.x0) / 2, (area.y1 - area.y0) / 2])
    tip = centre + direction * min(float(np.min(half / np.maximum(np.abs(direction), 1e-9))), 1.0)
    unit = direction / max(float(np.linalg.norm(direction)), 1e-9)
    normal = np.array([-unit[1], unit[0]])
    r = 2.0 * style.marker_px
    arrow = fixed(np.array([tip, tip - unit * r * 1.6 + normal * r * 0.8, tip - unit * r * 1.6 - normal * r * 0.8]))
    cv2.fillPoly(image, [arrow.reshape(-1, 1, 2)], colour, cv2.LINE_AA, SHIFT)
    cv2.polylines(image, [arrow.reshape(-1, 1, 2)], True, WHITE, 1, cv2.LINE_AA, SHIFT)


def _pt(p: FloatArray) -> tuple[int, int]:
    q = fixed(p)
    return int(q[0]), int(q[1])
