"""Pixel <-> normalised image coordinates (Hartley-style conditioning).

The linear equations of the method mix pixel-sized terms (x, y ~ 10^3) with the
homogeneous 1; in raw pixels the third row of Eq. 1 is swamped and the solution
loses several digits. Everything inside the solvers therefore runs in
coordinates centred on the principal point and divided by a scale derived from
the image size alone (not from the points), so that scaling an image and its
points by s leaves the normalised problem unchanged and f scales exactly by s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ImageFrame:
    """Principal point (pixels) and the conditioning scale (pixels per unit)."""

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


def homogeneous(points: FloatArray) -> FloatArray:
    """(N, 2) -> (N, 3) with a trailing 1."""
    return np.concatenate((points, np.ones(points.shape[:-1] + (1,))), axis=-1)
