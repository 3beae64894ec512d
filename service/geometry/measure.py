"""Ground positions and pairwise distances, with 1-sigma uncertainties, for any people seen by a calibrated camera.

This is what a frame's result is made of: each person is placed from the
ankle centre when it is visible (ray meets the ground plane), otherwise from
the shoulder centre (ray meets the plane raised by the height prior). The
uncertainty of each distance combines, to first order, the calibration's
covariance, the keypoint noise of both people and, for people placed from
their shoulders, the spread of real heights around the prior.

Not everyone stands: a seated person's shoulders are lower than a standing one's, and a person whose lower body
is hidden may be either. Callers say so per person (`height_scale`: the shoulders' height as a fraction of the
standing prior, `height_std_m`: how uncertain that height is), so such people are placed where their shoulders
put them and their distances carry the wider sigma that uncertainty implies. A person placed from a cue less
precise than an ankle keypoint (the bottom of the detector's box) says so with `contact_std_fraction`: the pixel
sigma of that point as a fraction of how tall (shoulder to ankle, in pixels) a person of the prior height stands
at their place. It is relative because the cue's error is a share of the person's size in the image, which the
camera predicts at any place; a stored person need not keep their box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .calibration import Calibration
from .model import tangent_basis
from .priors import DEFAULT_HEIGHT_STD_M
from .reconstruct import intersect_plane, pairwise_distances
from .uncertainty import CANONICAL_PARAMETERS, canonical_camera
from .vec import FloatArray

# Finite-difference steps of the keypoint-noise and height-spread terms.
_KEYPOINT_STEP_PX = 1e-4
_HEIGHT_STEP_M = 1e-4


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


@dataclass(frozen=True)
class _Variants:
    """K versions of the camera and of the people, evaluated together: the measurement and its finite
    differences (each perturbs one parameter) cost one vectorised pass instead of K small ones."""

    cameras: FloatArray  # (K, 8) canonical parameters (fx, fy, t1, t2, rho, cx, cy, k)
    normal: FloatArray  # (K, 3)
    height_m: FloatArray  # (K,)
    tops_px: FloatArray  # (K, N, 2)
    bottoms_px: FloatArray  # (K, N, 2)


def _positions(cal: Calibration, v: _Variants, from_ankles: FloatArray, height_scale: FloatArray) -> FloatArray:
    """(K, N, 3) camera-frame ground points: the ankle ray meets the plane; without ankles, the shoulder ray
    meets the plane raised by the height prior and the point is lowered back onto the ground."""
    chosen = np.where(from_ankles[:, None], v.bottoms_px, v.tops_px)
    if cal.lens is not None:
        chosen = cal.camera.undistort_px(chosen)  # the user's lens is exact: no variants
    c = v.cameras[:, None, :]
    scale_px = (cal.image_size[0] + cal.image_size[1]) / 4.0
    rel = np.stack(((chosen[..., 0] - c[..., 5]) / scale_px, (chosen[..., 1] - c[..., 6]) / scale_px), -1)
    k = c[..., 7]
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = 1.0 + k * np.sum(rel * rel, -1)
        rel = np.where((denom > 0)[..., None], rel / denom[..., None], np.nan)
    ray = np.stack(
        (rel[..., 0] * scale_px / c[..., 0], rel[..., 1] * scale_px / c[..., 1], np.ones(chosen.shape[:-1])), -1
    )
    lift_m = np.where(from_ankles, 0.0, v.height_m[:, None] * height_scale[None, :])  # (K, N)
    normal = v.normal[:, None, :]
    x = intersect_plane(ray, normal, v.cameras[:, 4:5] - lift_m)
    return x - lift_m[..., None] * normal


def _camera_steps(cal: Calibration, count: int) -> FloatArray:
    """Finite-difference steps in the first `count` canonical parameters."""
    return np.array([1e-6 * cal.fx, 1e-6 * cal.fy, 1e-7, 1e-7, 1e-7 * cal.rho, 1e-4, 1e-4, 1e-7])[:count]


def _variants(cal: Calibration, tops_px: FloatArray, bottoms_px: FloatArray, count: int) -> _Variants:
    """The base camera, then one step in each of the first `count` canonical parameters, then the people's
    keypoints moved along x and along y, then the height prior raised."""
    c0 = np.array([cal.fx, cal.fy, 0.0, 0.0, cal.rho, cal.cx, cal.cy, cal.distortion_k])
    cameras = [c0]
    steps = _camera_steps(cal, count)
    for k in range(count):
        c = c0.copy()
        c[k] += steps[k]
        cameras.append(c)
    cameras += [c0, c0, c0]
    basis = tangent_basis(cal.normal)
    normals = [canonical_camera(c, cal.normal, basis)[2] for c in cameras]
    moved_x, moved_y = np.array([_KEYPOINT_STEP_PX, 0.0]), np.array([0.0, _KEYPOINT_STEP_PX])
    shifts = [np.zeros(2)] * (len(cameras) - 3) + [moved_x, moved_y, np.zeros(2)]
    heights = np.full(len(cameras), cal.height_m)
    heights[-1] += _HEIGHT_STEP_M
    return _Variants(
        cameras=np.array(cameras),
        normal=np.array(normals),
        height_m=heights,
        tops_px=tops_px[None] + np.array(shifts)[:, None, :],
        bottoms_px=bottoms_px[None] + np.array(shifts)[:, None, :],
    )


def _standing_length_px(cal: Calibration, points: FloatArray) -> FloatArray:
    """(N,) shoulder-to-ankle length in pixels of a person of the prior height standing at each ground point
    (pinhole: the lens changes it by a few percent, below the precision of the cue it scales); 0 where unplaced."""
    tops = points + cal.height_m * cal.normal
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = [np.stack((cal.fx * p[:, 0] / p[:, 2], cal.fy * p[:, 1] / p[:, 2]), -1) for p in (points, tops)]
        return np.nan_to_num(np.hypot(*(uv[1] - uv[0]).T), nan=0.0)


def measure(
    cal: Calibration,
    tops: ArrayLike,
    bottoms: ArrayLike,
    noise_px: float | None = None,
    height_std_m: ArrayLike = DEFAULT_HEIGHT_STD_M,
    height_scale: ArrayLike = 1.0,
    contact_std_fraction: ArrayLike = 0.0,
) -> Measurement:
    """Place people and measure every pair. Rows of NaN mark keypoints that were not seen.

    noise_px defaults to the keypoint noise the calibration estimated from its
    own residuals; height_std_m is the spread of real shoulder heights around the
    prior (one value, or one per person), which matters only for people placed from
    their shoulders; height_scale (one value, or one per person, > 0) is each person's
    shoulder height as a fraction of the calibration's height prior (1 standing);
    contact_std_fraction (one value, or one per person) adds a pixel sigma to the point
    each person is placed from, as a fraction of their predicted standing height in pixels
    (see the module docstring).
    """
    tops_px = np.asarray(tops, dtype=np.float64).reshape(-1, 2)
    bottoms_px = np.asarray(bottoms, dtype=np.float64).reshape(-1, 2)
    from_ankles = np.all(np.isfinite(bottoms_px), axis=1)
    scale = np.broadcast_to(np.asarray(height_scale, dtype=np.float64), from_ankles.shape)
    std_m = np.broadcast_to(np.asarray(height_std_m, dtype=np.float64), from_ankles.shape)
    unc = cal.uncertainty
    sigma_px = (unc.noise_px if unc is not None else 0.0) if noise_px is None else noise_px
    count = 0 if unc is None else min(len(unc.covariance), len(CANONICAL_PARAMETERS))
    xs = _positions(cal, _variants(cal, tops_px, bottoms_px, count), from_ankles, scale)
    x0 = xs[0]
    dist = pairwise_distances(x0)
    n = len(x0)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = (x0[:, None, :] - x0[None, :, :]) / dist[..., None]
    var = np.zeros((n, n))

    if unc is not None:
        # Calibration: each person's sensitivity to the canonical parameters.
        dx_dc = np.moveaxis((xs[1 : count + 1] - x0) / _camera_steps(cal, count)[:, None, None], 0, -1)
        g = np.einsum("ijx,ixk->ijk", unit, dx_dc) - np.einsum("ijx,jxk->ijk", unit, dx_dc)
        var += np.einsum("ijk,kl,ijl->ij", g, np.asarray(unc.covariance)[:count, :count], g)

    # Keypoint noise on the point each person is placed from (growing with their size, see
    # service.geometry.posterior), and height spread for shoulder placement.
    dx_dpx = (xs[-3:-1] - x0) / _KEYPOINT_STEP_PX  # (2, N, 3): along x, along y
    per_length = 0.0 if unc is None else unc.noise_per_length
    length_px = np.nan_to_num(np.hypot(*(tops_px - bottoms_px).T), nan=0.0)
    sigma2 = sigma_px**2 + (per_length * length_px) ** 2
    contact = np.broadcast_to(np.asarray(contact_std_fraction, dtype=np.float64), from_ankles.shape)
    if np.any(contact > 0):
        sigma2 = sigma2 + (contact * _standing_length_px(cal, x0)) ** 2
    per_person = sigma2[:, None, None] * np.einsum("ani,anj->nij", dx_dpx, dx_dpx)
    # The last variant raises the prior by one step, each person's shoulders by `scale` steps.
    dx_dh = (xs[-1] - x0) / (_HEIGHT_STEP_M * scale[:, None])
    per_person += (std_m**2 * np.where(from_ankles, 0.0, 1.0))[:, None, None] * np.einsum("ni,nj->nij", dx_dh, dx_dh)
    var += np.einsum("ijx,ixy,ijy->ij", unit, per_person, unit) + np.einsum("ijx,jxy,ijy->ij", unit, per_person, unit)
    std = np.sqrt(np.maximum(var, 0.0))  # rounding can take a zero variance (two people at one spot) below 0
    np.fill_diagonal(std, 0.0)
    return Measurement(x0, from_ankles & np.all(np.isfinite(x0), axis=1), dist, std)
