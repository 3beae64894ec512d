"""Array types and broadcasting dot and cross products of 3-vectors along the last axis.

numpy's np.cross and reductions over a length-3 axis carry per-call overhead
that dominates at the array sizes here (a batch solve of 1000 people takes
about a millisecond); written out per component they are several times faster.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def dot(a: FloatArray, b: FloatArray) -> FloatArray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a: FloatArray, b: FloatArray) -> FloatArray:
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), -1)


def homogeneous(points: FloatArray) -> FloatArray:
    """(..., 2) -> (..., 3) with a trailing 1."""
    return np.concatenate((points, np.ones(points.shape[:-1] + (1,))), axis=-1)
