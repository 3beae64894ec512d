"""A measured frame's two pictures, drawn one way for the API (service.pictures) and `posemetry analyze`: the frame
with the ground grid, the people and their nearest-neighbour distances (overlay), and a map of where its people
stand (top-down). Both come from the frame's result and its people, so they can never disagree with the numbers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from service.domain import PersonIn, StoredCentres
from service.geometry.calibration import Calibration

from .grid import SIX_FEET_M
from .overlay import PersonMark, marks_from_result, render_overlay
from .topdown import TopDownView, render_topdown

if TYPE_CHECKING:
    from service.frames.schemas import FrameResult


def grid_cell_m(unit: str) -> float:
    """1 m cells for metres; 6 ft cells (the social-distancing unit) for feet."""
    return SIX_FEET_M if unit == "ft" else 1.0


@dataclass(frozen=True)
class FramePictures:
    """One frame as its pictures draw it: the calibration that measured it (None: not measured), its result, its
    people as marks, and the unit of the grid and the labels (`m` or `ft`)."""

    calibration: Calibration | None
    result: FrameResult
    marks: list[PersonMark]
    unit: str = "m"

    @classmethod
    def of(
        cls,
        result: FrameResult,
        people: Sequence[PersonIn | StoredCentres],
        calibration: Calibration | None,
        unit: str = "m",
    ) -> FramePictures:
        return cls(calibration, result, marks_from_result(result, people, calibration), unit)

    def overlay(self, image_bgr: np.ndarray) -> np.ndarray:
        """The frame with the ground grid, people coloured by the threshold and nearest-neighbour links."""
        return render_overlay(
            image_bgr,
            self.calibration,
            self.marks,
            self.result.pairs,
            self.result.distance_threshold_m,
            grid_cell_m=grid_cell_m(self.unit),
            unit=self.unit,
        )

    def topdown(self, *, size_px: int = 800, view: TopDownView | None = None, title: str | None = None) -> np.ndarray:
        """A map of where the frame's people stand, `size_px` square or in the given view, headed by `title`."""
        return render_topdown(
            self.marks,
            self.result.pairs,
            self.result.distance_threshold_m,
            size_px=size_px,
            calibration=self.calibration,
            view=view,
            grid_m=grid_cell_m(self.unit),
            unit=self.unit,
            title=title,
        )
