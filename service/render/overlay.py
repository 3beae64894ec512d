"""A camera frame annotated as in Fig. 1 of Fei et al.: ground grid, people boxes, nearest-neighbour distances.

The picture is what an operator checks a calibration by: a grid that lies flat on the pavement and shrinks
towards the horizon says the ground plane is right, boxes coloured by the threshold and labelled links say
what the service concluded. Everything is computed from the same stored result the API serves, so the picture
can never disagree with the numbers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import cv2
import numpy as np

from service.domain import PersonIn, StoredCentres, centres
from service.geometry.calibration import Calibration

from .grid import grid_segments
from .ground import GroundFrame
from .style import CYAN, GREEN, LIGHT_RED, PINK, RED, SHIFT, Style, fixed, format_distance, label, line

if TYPE_CHECKING:
    from service.frames.schemas import FrameResult

# COCO-17 keypoints below this score are not used to size a box (same cut-off as service.frames.keypoints).
MIN_KEYPOINT_SCORE = 0.3
# Box proportions from the shoulder-to-ankle segment L (shoulder ~0.82, ankle ~0.04 of stature):
# the head top is ~0.23 L above the shoulders, the feet ~0.05 L below the ankles, a person ~0.45 L wide.
_HEAD_ABOVE = 0.23
_FEET_BELOW = 0.05
_HALF_WIDTH = 0.22

Point = tuple[float, float]
Box = tuple[float, float, float, float]


class PairLike(Protocol):
    """A measured pair (service.frames.schemas.PairDistance has this shape)."""

    i: int
    j: int
    distance_m: float | None


@dataclass(frozen=True)
class PersonMark:
    """What the drawings need of one person.

    `index` is the person's index in the frame (pairs refer to it); `ground_m` is the stored (right, forward)
    ground position; `foot_px` the pixel where the person meets the ground (ankle centre, or the projection of
    the ground position when the ankles were hidden); `box_px` (x0, y0, x1, y1) is optional: keypoint-only
    frames have none unless it can be derived, and a person without a box is drawn as a marker.
    """

    index: int
    ground_m: Point | None = None
    foot_px: Point | None = None
    box_px: Box | None = None
    shoulder_px: Point | None = None


def box_from_keypoints(keypoints: Sequence[Sequence[float]], min_score: float = MIN_KEYPOINT_SCORE) -> Box | None:
    """Bounding box of the confident COCO-17 keypoints, padded to cover head and feet; None if under 3 points.

    Keypoints sit on joints, so their hull misses the top of the head and the shoes: pad by 12% of the hull's
    height above, 5% below and 10% of it on each side.
    """
    points = np.array([(k[0], k[1]) for k in keypoints if len(k) >= 3 and k[2] >= min_score], dtype=float)
    if len(points) < 3:
        return None
    x0, y0 = points.min(axis=0)
    x1, y1 = points.max(axis=0)
    h = max(y1 - y0, 1.0)
    return (x0 - 0.1 * h, y0 - 0.12 * h, x1 + 0.1 * h, y1 + 0.05 * h)


def box_from_segment(shoulder: Point, foot: Point) -> Box | None:
    """A person-shaped box around the shoulder-to-foot segment (body proportions above); None if degenerate."""
    length = math.hypot(foot[0] - shoulder[0], foot[1] - shoulder[1])
    if not length > 1.0:
        return None
    xs = (shoulder[0], foot[0])
    top = min(shoulder[1], foot[1]) - _HEAD_ABOVE * length
    bottom = max(shoulder[1], foot[1]) + _FEET_BELOW * length
    return (min(xs) - _HALF_WIDTH * length, top, max(xs) + _HALF_WIDTH * length, bottom)


def marks_from_result(
    result: FrameResult,
    people: Sequence[PersonIn | StoredCentres],
    calibration: Calibration | None = None,
) -> list[PersonMark]:
    """PersonMarks for a stored frame: its `FrameResult` plus its stored people in person-index order.

    Boxes are the detector's (people found in an image), else the hull of the stored keypoints, else derived
    from shoulder and foot. With `calibration`, people whose ankles were hidden get a foot pixel by projecting
    their stored ground point (`point_m`) into the image.
    """
    frame = GroundFrame.from_calibration(calibration) if calibration is not None else None
    positions = {p.index: p for p in result.people}
    marks = []
    for index, person in enumerate(people):
        shoulder, ankle = centres(person)
        position = positions.get(index)
        foot = ankle
        if foot is None and frame is not None and position is not None and position.point_m is not None:
            px = frame.camera_to_pixels(np.array(position.point_m))
            foot = (float(px[0]), float(px[1])) if np.all(np.isfinite(px)) else None
        box = getattr(person, "box_px", None)  # the detector's box, for people found in an image
        if box is None and person.keypoints:
            box = box_from_keypoints(person.keypoints)
        if box is None and shoulder is not None and foot is not None:
            box = box_from_segment(shoulder, foot)
        ground = position.ground_m if position is not None else None
        marks.append(PersonMark(index=index, ground_m=ground, foot_px=foot, box_px=box, shoulder_px=shoulder))
    return marks


def violators(pairs: Sequence[PairLike], threshold_m: float) -> set[int]:
    """Indices of people in at least one pair strictly closer than the threshold (as service.frames.measure counts)."""
    out: set[int] = set()
    for p in pairs:
        if p.distance_m is not None and math.isfinite(p.distance_m) and p.distance_m < threshold_m:
            out.update((p.i, p.j))
    return out


def nearest_neighbours(pairs: Sequence[PairLike], indices: Sequence[int]) -> list[tuple[int, int, float]]:
    """Each person's nearest neighbour as (i, j, distance_m) with i < j, mutual pairs listed once."""
    wanted = set(indices)
    best: dict[int, tuple[float, int]] = {}
    for p in pairs:
        if p.distance_m is None or not math.isfinite(p.distance_m) or p.i not in wanted or p.j not in wanted:
            continue
        for a, b in ((p.i, p.j), (p.j, p.i)):
            if a not in best or p.distance_m < best[a][0]:
                best[a] = (p.distance_m, b)
    links = {(min(a, b), max(a, b)): d for a, (d, b) in best.items()}
    return [(i, j, d) for (i, j), d in sorted(links.items())]


def draw_grid(
    image: np.ndarray,
    frame: GroundFrame,
    style: Style,
    cell_m: float,
    *,
    color: tuple[int, int, int] = CYAN,
    max_range_m: float | None = None,
    opacity: float = 0.85,
) -> None:
    """Blend the ground grid into `image` (in place), fading with distance from the camera."""
    segments = grid_segments(frame, cell_m, max_range_m=max_range_m)
    if not segments:
        return
    reach = max(float(s.range_m.max()) for s in segments)
    alpha = np.zeros(image.shape[:2], dtype=np.uint8)
    for s in segments:
        # Near lines at full opacity, the farthest at a quarter: depth reads at a glance, clutter fades.
        fade = opacity * (1.0 - 0.75 * np.clip(0.5 * (s.range_m[:-1] + s.range_m[1:]) / reach, 0.0, 1.0))
        points = [tuple(p) for p in fixed(s.pixels).tolist()]
        values = np.rint(255 * fade).astype(int).tolist()
        for k, value in enumerate(values):
            cv2.line(alpha, points[k], points[k + 1], value, style.thin_px, cv2.LINE_AA, SHIFT)
    a = alpha.astype(np.float32)[..., None] / 255.0
    blended = image.astype(np.float32) * (1.0 - a) + np.array(color, dtype=np.float32) * a
    image[...] = np.round(blended).astype(np.uint8)


def render_overlay(
    image_bgr: np.ndarray,
    calibration: Calibration | None,
    people: Sequence[PersonMark],
    pairs: Sequence[PairLike],
    threshold_m: float,
    *,
    grid_cell_m: float = 1.0,
    unit: str = "m",
    grid_range_m: float | None = None,
) -> np.ndarray:
    """A copy of the frame with the ground grid, people coloured by the threshold and nearest-neighbour links.

    `grid_cell_m`: 1.0 for a metre grid or `grid.SIX_FEET_M` for the paper's 6 ft cells; `unit` ("m" or "ft")
    for the distance labels. With `calibration` None no grid is drawn. The calibration may be for a larger or
    smaller image than `image_bgr` (a thumbnail): intrinsics are rescaled, but pixel coordinates in `people`
    must be in `image_bgr`'s pixels.
    """
    image = np.ascontiguousarray(image_bgr)
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    image = image.astype(np.uint8, copy=True)
    height, width = image.shape[:2]
    style = Style.for_size(width, height)
    if calibration is not None:
        frame = GroundFrame.from_calibration(calibration, (width, height))
        draw_grid(image, frame, style, grid_cell_m, max_range_m=grid_range_m)

    red = violators(pairs, threshold_m)
    anchors = {p.index: p.foot_px if p.foot_px is not None else p.shoulder_px for p in people}
    drawable = [i for i, a in anchors.items() if a is not None]
    links = nearest_neighbours(pairs, drawable)
    for i, j, d in links:
        color = RED if d < threshold_m else PINK
        line(image, np.array(anchors[i]), np.array(anchors[j]), color, style.line_px)

    for person in people:
        color = RED if person.index in red else GREEN
        if person.box_px is not None:
            x0, y0, x1, y1 = person.box_px
            corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
            cv2.polylines(image, [_fixed_poly(corners)], True, color, style.line_px, cv2.LINE_AA, SHIFT)
        anchor = anchors[person.index]
        if anchor is not None:
            radius = style.marker_px if person.box_px is None else max(2, style.marker_px // 2)
            cv2.circle(image, _fixed_point(anchor), radius << SHIFT, color, -1, cv2.LINE_AA, SHIFT)
    for i, j, d in links:
        a, b = np.array(anchors[i]), np.array(anchors[j])
        mid = (a + b) / 2
        text_color = LIGHT_RED if d < threshold_m else PINK
        label(image, format_distance(d, unit), (float(mid[0]), float(mid[1])), style, color=text_color)
    return image


def _fixed_point(p: Point) -> tuple[int, int]:
    q = fixed(np.array(p))
    return int(q[0]), int(q[1])


def _fixed_poly(points: np.ndarray) -> np.ndarray:
    return fixed(points).reshape(-1, 1, 2)
