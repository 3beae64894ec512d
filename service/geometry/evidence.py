"""Which stored observations are independent evidence: one person standing still is one person, not hundreds.

Calibration treats every observation as an independent draw of a person's shoulder-over-ankle segment. A fixed
camera breaks that in two ways: someone who stands still (waiting at a door) is seen in hundreds of frames with
the same pixels, and a static false detection (a mannequin in a shop window, a poster) is "seen" in every frame.
Either then outweighs dozens of real passers-by, and a static false positive that happens to look plausible
drags the solution (seen on the Oxford Town Centre clip: one mannequin in 82 frames moved fx by 10 % and the
ground normal by 1.7 degrees). Collapsing repeats keeps one observation per place and pose: anything whose
shoulder and ankle both lie within `radius_px` of an observation already kept is a repeat. Walking people move
several pixels between frames, so their observations survive; still ones collapse to one.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# Pose-model jitter on a still person is 1-3 px at 1080p; this is comfortably above it as a share of the image.
DEFAULT_RADIUS_FRACTION = 0.002


def repeat_radius_px(image_size_px: tuple[float, float]) -> float:
    """The default radius for an image: DEFAULT_RADIUS_FRACTION of its diagonal (4.4 px at 1920x1080)."""
    return DEFAULT_RADIUS_FRACTION * float(np.hypot(*image_size_px))


def collapse_repeats(tops_px: np.ndarray, bottoms_px: np.ndarray, radius_px: float) -> np.ndarray:
    """Indices (ascending) of the observations to keep: the first of every group of repeats, in input order.

    A repeat is within `radius_px` of a kept observation in every coordinate of both points (Chebyshev distance
    on the 4-vector shoulder x, y, ankle x, y), so two people who merely share a spot but differ in height or lean
    are both kept. Rows with non-finite coordinates are kept as they are (the caller's validation handles them).
    """
    points = np.hstack([np.asarray(tops_px, dtype=float), np.asarray(bottoms_px, dtype=float)])
    n = len(points)
    if n == 0 or radius_px <= 0:
        return np.arange(n)
    finite = np.all(np.isfinite(points), axis=1)
    finite_index = np.flatnonzero(finite)
    tree = cKDTree(points[finite])
    neighbours = tree.query_ball_point(points[finite], r=radius_px, p=np.inf)
    suppressed = np.zeros(len(finite_index), dtype=bool)
    keep = np.zeros(n, dtype=bool)
    keep[~finite] = True
    for local, others in enumerate(neighbours):
        if suppressed[local]:
            continue
        keep[finite_index[local]] = True
        suppressed[others] = True
    return np.flatnonzero(keep)
