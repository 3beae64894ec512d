"""Ground positions and pairwise distances, with 1-sigma uncertainties, for any people seen by a calibrated camera.

This is what a frame's result is made of: each person is placed from the
ankle centre when it is visible (ray meets the ground plane), otherwise from
the shoulder centre (ray meets the plane raised by the height prior). The
uncertainty of each distance combines, to first order, the calibration's
covariance, the keypoint noise of both people and, for people placed from
their shoulders, the spread of real heights around the prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .calibration import Calibration
from .frame import FloatArray
from .priors import DEFAULT_HEIGHT_STD_M
from .reconstruct import intersect_plane, pairwise_distances
from .uncertainty import canonical_camera


@dataclass(frozen=True)
class Measurement:
    """Per-person positions (camera frame, metres) and (N, N) distance matrices; NaN where unplaced."""

    points_bottom: FloatArray
    from_ankles: FloatArray  # (N,) bool: placed from the ankle centre (else from the shoulders, or not at all)
    distances_m: FloatArray
    distance_std_m: FloatArray

    @property
    def placed(self) -> FloatArray:
        return np.all(np.isfinite(self.points_bottom), axis=1)


def _positions(
    c: FloatArray,
    cal: Calibration,
    tops_px: FloatArray,
    bottoms_px: FloatArray,
    from_ankles: FloatArray,
    height_m: float,
) -> FloatArray:
    fx, fy, normal, rho = canonical_camera(c, cal.normal)
    chosen = np.where(from_ankles[:, None], bottoms_px, tops_px)
    chosen = undistort_px(cal, chosen)
    ray = np.stack(((chosen[:, 0] - cal.cx) / fx, (chosen[:, 1] - cal.cy) / fy, np.ones(len(chosen))), -1)
    offset = np.where(from_ankles, rho, rho - height_m)
    x = intersect_plane(ray, normal, offset)
    return x - np.where(from_ankles, 0.0, height_m)[:, None] * normal


def undistort_px(cal: Calibration, points_px: FloatArray) -> FloatArray:
    """Division-model undistortion around the principal point (identity when distortion_k == 0)."""
    if cal.distortion_k == 0.0:
        return points_px
    from .distortion import undistort
    from .frame import ImageFrame

    frame = ImageFrame.from_size(cal.image_size, (cal.cx, cal.cy))
    return frame.to_pixels(undistort(frame.normalise(points_px), cal.distortion_k))


def measure(
    cal: Calibration,
    tops: ArrayLike,
    bottoms: ArrayLike,
    noise_px: float | None = None,
    height_std_m: float = DEFAULT_HEIGHT_STD_M,
) -> Measurement:
    """Place people and measure every pair. Rows of NaN mark keypoints that were not seen.

    noise_px defaults to the keypoint noise the calibration estimated from its
    own residuals; height_std_m is the spread of real heights around the prior,
    which matters only for people placed from their shoulders.
    """
    tops_px = np.asarray(tops, dtype=np.float64).reshape(-1, 2)
    bottoms_px = np.asarray(bottoms, dtype=np.float64).reshape(-1, 2)
    from_ankles = np.all(np.isfinite(bottoms_px), axis=1)
    unc = cal.uncertainty
    sigma_px = (unc.noise_px if unc is not None else 0.0) if noise_px is None else noise_px
    c0 = np.array([cal.fx, cal.fy, 0.0, 0.0, cal.rho])
    x0 = _positions(c0, cal, tops_px, bottoms_px, from_ankles, cal.height_m)
    dist = pairwise_distances(x0)
    n = len(x0)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = (x0[:, None, :] - x0[None, :, :]) / dist[..., None]
    var = np.zeros((n, n))

    if unc is not None:
        # Calibration: each person's sensitivity to the 5 canonical parameters.
        steps = np.array([1e-6 * cal.fx, 1e-6 * cal.fy, 1e-7, 1e-7, 1e-7 * cal.rho])
        dx_dc = np.empty((n, 3, 5))
        for k in range(5):
            c = c0.copy()
            c[k] += steps[k]
            dx_dc[:, :, k] = (_positions(c, cal, tops_px, bottoms_px, from_ankles, cal.height_m) - x0) / steps[k]
        g = np.einsum("ijx,ixk->ijk", unit, dx_dc) - np.einsum("ijx,jxk->ijk", unit, dx_dc)
        var += np.einsum("ijk,kl,ijl->ij", g, unc.covariance, g)

    # Keypoint noise on the point each person is placed from, and height spread for shoulder placement.
    per_person = np.zeros((n, 3, 3))
    for axis in (0, 1):
        step = 1e-4
        t, b = tops_px.copy(), bottoms_px.copy()
        t[:, axis] += step
        b[:, axis] += step
        dx = (_positions(c0, cal, t, b, from_ankles, cal.height_m) - x0) / step
        per_person += sigma_px**2 * np.einsum("ni,nj->nij", dx, dx)
    dx_dh = (_positions(c0, cal, tops_px, bottoms_px, from_ankles, cal.height_m + 1e-4) - x0) / 1e-4
    per_person += (height_std_m**2 * np.where(from_ankles, 0.0, 1.0))[:, None, None] * np.einsum(
        "ni,nj->nij", dx_dh, dx_dh
    )
    var += np.einsum("ijx,ixy,ijy->ij", unit, per_person, unit) + np.einsum("ijx,jxy,ijy->ij", unit, per_person, unit)
    std = np.sqrt(var)
    np.fill_diagonal(std, 0.0)
    return Measurement(x0, from_ankles & np.all(np.isfinite(x0), axis=1), dist, std)
