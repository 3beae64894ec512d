"""How alike two people look: the distance between appearance descriptors (pure numpy).

A descriptor (computed from the frame's pixels by service/pose/appearance.py) is a colour histogram of two body
regions, torso (shoulders to hips) and legs (hips to ankles), each APPEARANCE_BINS (hue x saturation x value)
bins over HSV, stored as DESCRIPTOR_BYTES uint8 values: per region, round(255 sqrt(p)) of the normalised
histogram p. Storing square roots makes the Bhattacharyya coefficient of two regions a dot product (sum of
sqrt(p q)), and 128 bytes per person keep the store small. Quantising moves a distance by about 0.01, well under
the gap between one person's distances and strangers' (median 0.26 vs 0.89 on Town Centre).

Regions are compared separately (the Bhattacharyya distance sqrt(1 - BC), as OpenCV's HISTCMP_BHATTACHARYYA)
and the larger of the two distances counts: two strangers in the same dark coat differ in their trousers, and a
match must hold for both.
"""

from __future__ import annotations

import numpy as np

APPEARANCE_BINS = (8, 2, 4)
"""Hue, saturation, value bins of each region's histogram. Two saturation bins (grey or coloured): on Town Centre
four of them, which split one coat's saturation as light and JPEG blur shift it, linked 32 % of one person's pairs
across frames at the distance that links 54 % with two, the strangers linked being the same (one look-alike
couple); one bin did as well as two (docs/benchmarks/camera-model.md)."""
REGION_BINS = APPEARANCE_BINS[0] * APPEARANCE_BINS[1] * APPEARANCE_BINS[2]
APPEARANCE_REGIONS = ("torso", "legs")
DESCRIPTOR_BYTES = REGION_BINS * len(APPEARANCE_REGIONS)
_SCALE = 255.0


def encode_descriptor(histograms: np.ndarray) -> bytes:
    """(regions, REGION_BINS) non-negative histograms (any scale, each with mass) as the stored bytes."""
    hist = np.asarray(histograms, dtype=np.float64).reshape(len(APPEARANCE_REGIONS), REGION_BINS)
    total = hist.sum(axis=1, keepdims=True)
    if np.any(total <= 0):
        raise ValueError("every region needs pixels")
    return np.round(_SCALE * np.sqrt(hist / total)).astype(np.uint8).tobytes()


def decode_descriptors(descriptors: list[bytes | None]) -> tuple[np.ndarray, np.ndarray]:
    """(n, regions, REGION_BINS) unit vectors (sqrt of each region's histogram) and (n,) bool: has a descriptor.

    A missing descriptor or one of another length (written by another layout) counts as none."""
    n = len(descriptors)
    roots = np.zeros((n, len(APPEARANCE_REGIONS), REGION_BINS))
    present = np.zeros(n, dtype=bool)
    for i, descriptor in enumerate(descriptors):
        if descriptor is None or len(descriptor) != DESCRIPTOR_BYTES:
            continue
        vector = np.frombuffer(descriptor, dtype=np.uint8).astype(np.float64).reshape(roots.shape[1:])
        norms = np.linalg.norm(vector, axis=1, keepdims=True)
        if np.all(norms > 0):
            roots[i], present[i] = vector / norms, True
    return roots, present


def appearance_distances(roots_a: np.ndarray, roots_b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) distances in [0, 1] between decoded descriptors: the larger of the regions' Bhattacharyya
    distances (0 for equal histograms, 1 for ones without a common bin)."""
    # The larger distance is the smaller coefficient: one matrix product per region, in float32 (a long-gap link
    # compares every open chain with every new track; float32 moves a coefficient by ~1e-7, so a distance near 0 by
    # up to ~5e-4 through the square root, against links judged to ~1e-2).
    regions = range(roots_a.shape[1])
    a, b = (np.ascontiguousarray(np.swapaxes(roots, 0, 1), dtype=np.float32) for roots in (roots_a, roots_b))
    coefficient = np.minimum.reduce([a[r] @ b[r].T for r in regions]).astype(np.float64)
    return np.sqrt(np.clip(1.0 - coefficient, 0.0, 1.0))
