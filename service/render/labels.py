"""Label placement that never overlaps: each label goes to the first free spot near its anchor, or is left out.

Greedy, in the caller's order of importance: for each label, candidate boxes are tried from its anchor outwards
(on the anchor, then on rings of growing radius around it), and the first one that lies inside the bounds and meets
no obstacle and no label already placed is taken. A label with no free candidate is not drawn, and the caller says
how many were left out. So no two placed boxes ever intersect, by construction: every box placed was checked
against every box placed before it, with the same integer rectangles that are then drawn. Greedy is not optimal
(a different order might fit more labels), but it is predictable, puts the most important labels nearest their
anchors, and costs O(labels^2 x candidates), a few milliseconds for a crowded frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Box:
    """An integer pixel rectangle, inclusive: x0 <= x <= x1, y0 <= y <= y1."""

    x0: int
    y0: int
    x1: int
    y1: int

    def intersects(self, other: Box, gap_px: int = 0) -> bool:
        """Whether the boxes share a pixel, or come closer than `gap_px`."""
        return not (
            self.x1 + gap_px < other.x0
            or other.x1 + gap_px < self.x0
            or self.y1 + gap_px < other.y0
            or other.y1 + gap_px < self.y0
        )

    def inside(self, bounds: Box) -> bool:
        return bounds.x0 <= self.x0 and self.x1 <= bounds.x1 and bounds.y0 <= self.y0 and self.y1 <= bounds.y1

    @property
    def centre(self) -> tuple[float, float]:
        return (self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2


def box_at(centre: tuple[float, float], size: tuple[int, int]) -> Box:
    """The box of `size` (width, height) px centred, to the pixel, on `centre`."""
    w, h = size
    x0 = round(centre[0] - w / 2)
    y0 = round(centre[1] - h / 2)
    return Box(x0, y0, x0 + w - 1, y0 + h - 1)


# Candidate directions around an anchor: above first (a label above a line reads best), then below, the sides and
# the diagonals.
_DIRECTIONS = ((0, -1), (0, 1), (1, 0), (-1, 0), (1, -1), (-1, -1), (1, 1), (-1, 1))


def candidates(anchor: tuple[float, float], size: tuple[int, int], rings: int, step_px: float) -> list[Box]:
    """Boxes centred on the anchor, then around it on `rings` rings `step_px` apart (each ring also tries the
    directions between those of _DIRECTIONS, as it grows)."""
    w, h = size
    found = [box_at(anchor, size)]
    for ring in range(1, rings + 1):
        n = 8 * ring
        ordered = list(_DIRECTIONS) + [
            (math.cos(2 * math.pi * k / n), math.sin(2 * math.pi * k / n)) for k in range(n) if ring > 1
        ]
        for dx, dy in ordered:
            norm = math.hypot(dx, dy)
            ux, uy = dx / norm, dy / norm
            # Move far enough that the box clears the anchor along this direction, then `ring - 1` steps further.
            reach = abs(ux) * w / 2 + abs(uy) * h / 2 + step_px * (ring - 1) + 2
            found.append(box_at((anchor[0] + ux * reach, anchor[1] + uy * reach), size))
    return found


def place_labels(
    sizes: Sequence[tuple[int, int]],
    anchors: Sequence[tuple[float, float]],
    bounds: Box,
    obstacles: Sequence[Box] = (),
    *,
    rings: int = 4,
    step_px: float | None = None,
    gap_px: int = 1,
) -> list[Box | None]:
    """A box per label (None: no free spot), in the given order of importance; no two boxes intersect or come
    closer than `gap_px`, none meets an obstacle, all lie inside `bounds`."""
    if len(sizes) != len(anchors):
        raise ValueError("one anchor per label")
    placed: list[Box] = []
    out: list[Box | None] = []
    for size, anchor in zip(sizes, anchors, strict=True):
        step = step_px if step_px is not None else size[1] + gap_px
        chosen = None
        for box in candidates(anchor, size, rings, step):
            if (
                box.inside(bounds)
                and not any(box.intersects(o) for o in obstacles)
                and not any(box.intersects(p, gap_px) for p in placed)
            ):
                chosen = box
                break
        if chosen is not None:
            placed.append(chosen)
        out.append(chosen)
    return out
