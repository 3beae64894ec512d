"""Minimal solvers: a camera from the fewest people that determine it, many samples at once.

Two people determine the camera when the pixels are square or the focal
length is known (two segments meet in the vertical vanishing point v; Eq. 1
gives their depths up to one scale and Eq. 3 the single focal length); three
are needed when fx != fy. The steps after v are the batch solver's own
(service.geometry.linear), written over a leading sample axis, so a minimal
solution is exact on noise-free data and RANSAC solves 128 samples in a few
numpy passes. Invalid samples (coincident lines, no real focal length) come
back as NaN rows rather than exceptions.
"""

from __future__ import annotations

import numpy as np

from .linear import focal_weights, normal_and_rho, scaled_depths, segment_lines
from .vec import FloatArray


def minimal_size(equal_focal: bool, focal_known: bool) -> int:
    return 2 if (equal_focal or focal_known) else 3


def solve_minimal(
    tops_h: FloatArray,
    bottoms_h: FloatArray,
    height_m: float,
    equal_focal: bool,
    focal_n: tuple[float, float] | None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Hypotheses from (M, m, 3) minimal samples: focal (M, 2), normal (M, 3), rho (M,), v (M, 3)."""
    lines = segment_lines(tops_h, bottoms_h)
    lines = lines / np.linalg.norm(lines, axis=-1, keepdims=True)
    if lines.shape[1] == 2:
        v = np.cross(lines[:, 0], lines[:, 1])
        distinct = np.linalg.norm(v, axis=-1) > 1e-9
    else:
        eigval, eigvec = np.linalg.eigh(np.einsum("mni,mnj->mij", lines, lines))
        v = eigvec[..., 0]
        distinct = eigval[:, 1] > 1e-9 * eigval[:, 2]
    # Coincident image lines (two people on one line) say nothing about v.
    v = np.where(distinct[:, None], v, np.nan)
    with np.errstate(invalid="ignore"):
        v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    v3 = v[:, None, :]
    lam_t, lam_b = scaled_depths(tops_h, bottoms_h, v3, height_m)
    if focal_n is None:
        w = focal_weights(bottoms_h, lam_b, v3, equal_focal)
        with np.errstate(invalid="ignore"):
            focal = np.where(w > 0, 1.0 / np.sqrt(np.where(w > 0, w, 1.0)), np.nan)
    else:
        focal = np.broadcast_to(np.asarray(focal_n, dtype=np.float64), (len(v), 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        normal, rho = normal_and_rho(tops_h, bottoms_h, v3, lam_t, lam_b, focal, height_m)
    return focal, normal, rho, v
