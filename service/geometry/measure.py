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

`measure_many` measures the people of many frames (a measuring job's chunk) in one pass: what depends only on the
camera (its variants, steps, covariance) is done once, the per-person and per-pair work in a few vectorised array
operations over the whole chunk, and pairs are formed only within a frame. `measure` is that with one frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .calibration import Calibration
from .model import tangent_basis
from .priors import DEFAULT_HEIGHT_STD_M
from .reconstruct import intersect_plane
from .uncertainty import CANONICAL_PARAMETERS, canonical_camera
from .vec import FloatArray, dot

IntArray = NDArray[np.intp]

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
class Measurements:
    """The people of many frames measured together: per person (rows of all frames, frame after frame) and per
    pair (i < j within one frame, frame after frame, row-major within a frame, as np.triu_indices orders them).

    Pairs are vectors, not one (N, N) matrix per frame, so that a chunk costs one array operation per term and
    its results can be read frame by frame without copying: frame f's people are rows
    `frame_starts[f]:frame_starts[f + 1]` and its pairs `pair_starts[f]:pair_starts[f + 1]`.
    """

    points_bottom: FloatArray  # (N, 3) camera frame, metres; NaN rows unplaced
    from_ankles: FloatArray  # (N,) bool: placed from the ankle centre
    frame_starts: IntArray  # (F + 1,)
    first: IntArray  # (P,) row of each pair's first person (global: an index into points_bottom)
    second: IntArray  # (P,) row of its second person, in the same frame
    pair_starts: IntArray  # (F + 1,)
    distances_m: FloatArray  # (P,) NaN where either person is unplaced
    distance_std_m: FloatArray  # (P,)


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


@lru_cache(maxsize=128)
def _pairs_of(n: int) -> tuple[IntArray, IntArray]:
    """The pairs i < j of n people (cached: a chunk's frames have few distinct sizes)."""
    return np.triu_indices(n, 1)


def _frame_pairs(counts: IntArray) -> tuple[IntArray, IntArray, IntArray, IntArray]:
    """(frame_starts, first, second, pair_starts): the pairs within each frame of `counts` people, as rows."""
    frame_starts = np.concatenate(([0], np.cumsum(counts))).astype(np.intp)
    pair_counts = counts * (counts - 1) // 2
    pair_starts = np.concatenate(([0], np.cumsum(pair_counts))).astype(np.intp)
    parts = [_pairs_of(int(n)) for n in counts]
    offsets = np.repeat(frame_starts[:-1], pair_counts)
    first = np.concatenate([i for i, _ in parts]).astype(np.intp) + offsets if parts else np.zeros(0, np.intp)
    second = np.concatenate([j for _, j in parts]).astype(np.intp) + offsets if parts else np.zeros(0, np.intp)
    return frame_starts, first, second, pair_starts


def _per_person(values: ArrayLike, n: int) -> FloatArray:
    return np.broadcast_to(np.asarray(values, dtype=np.float64), (n,))


def measure_many(
    cal: Calibration,
    tops: ArrayLike,
    bottoms: ArrayLike,
    people_per_frame: ArrayLike,
    noise_px: float | None = None,
    height_std_m: ArrayLike = DEFAULT_HEIGHT_STD_M,
    height_scale: ArrayLike = 1.0,
    contact_std_fraction: ArrayLike = 0.0,
) -> Measurements:
    """Place the people of many frames and measure every pair within each frame (see `measure`, which this is
    for one frame). `tops` and `bottoms` hold all frames' people, frame after frame; `people_per_frame` says how
    many each frame has; the per-person arguments are one value or one per person (all frames)."""
    tops_px = np.asarray(tops, dtype=np.float64).reshape(-1, 2)
    bottoms_px = np.asarray(bottoms, dtype=np.float64).reshape(-1, 2)
    counts = np.asarray(people_per_frame, dtype=np.intp).reshape(-1)
    n = len(tops_px)
    if len(bottoms_px) != n or np.any(counts < 0) or int(counts.sum()) != n:
        raise ValueError(f"{n} tops and {len(bottoms_px)} bottoms for frames of {counts.tolist()} people")
    frame_starts, first, second, pair_starts = _frame_pairs(counts)
    from_ankles = np.all(np.isfinite(bottoms_px), axis=1)
    scale, std_m = _per_person(height_scale, n), _per_person(height_std_m, n)
    unc = cal.uncertainty
    sigma_px = (unc.noise_px if unc is not None else 0.0) if noise_px is None else noise_px
    count = 0 if unc is None else min(len(unc.covariance), len(CANONICAL_PARAMETERS))
    xs = _positions(cal, _variants(cal, tops_px, bottoms_px, count), from_ankles, scale)
    x0 = xs[0]
    diff = x0[first] - x0[second]
    dist = np.sqrt(dot(diff, diff))
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = diff / dist[:, None]
    var = np.zeros(len(first))

    if unc is not None:
        # Calibration: each person's sensitivity to the canonical parameters.
        # (N, C, 3) in memory, read as (N, 3, C): np.take gathers each pair's rows twice as fast as fancy indexing,
        # in the layout fancy indexing gives, so einsum sums in the same order (results do not move by an ulp).
        dx_dc = np.ascontiguousarray(
            np.moveaxis((xs[1 : count + 1] - x0) / _camera_steps(cal, count)[:, None, None], 0, 1)
        )
        g = np.einsum("px,pxk->pk", unit, dx_dc.take(first, axis=0).transpose(0, 2, 1)) - np.einsum(
            "px,pxk->pk", unit, dx_dc.take(second, axis=0).transpose(0, 2, 1)
        )
        var += np.einsum("pk,kl,pl->p", g, np.asarray(unc.covariance)[:count, :count], g)

    # Keypoint noise on the point each person is placed from (growing with their size, see
    # service.geometry.posterior), and height spread for shoulder placement.
    dx_dpx = (xs[-3:-1] - x0) / _KEYPOINT_STEP_PX  # (2, N, 3): along x, along y
    per_length = 0.0 if unc is None else unc.noise_per_length
    length_px = np.nan_to_num(np.hypot(*(tops_px - bottoms_px).T), nan=0.0)
    sigma2 = sigma_px**2 + (per_length * length_px) ** 2
    contact = _per_person(contact_std_fraction, n)
    if np.any(contact > 0):
        sigma2 = sigma2 + (contact * _standing_length_px(cal, x0)) ** 2
    per_person = sigma2[:, None, None] * np.einsum("ani,anj->nij", dx_dpx, dx_dpx)
    # The last variant raises the prior by one step, each person's shoulders by `scale` steps.
    dx_dh = (xs[-1] - x0) / (_HEIGHT_STEP_M * scale[:, None])
    per_person += (std_m**2 * np.where(from_ankles, 0.0, 1.0))[:, None, None] * np.einsum("ni,nj->nij", dx_dh, dx_dh)
    var += np.einsum("px,pxy,py->p", unit, per_person.take(first, axis=0), unit) + np.einsum(
        "px,pxy,py->p", unit, per_person.take(second, axis=0), unit
    )
    std = np.sqrt(np.maximum(var, 0.0))  # rounding can take a zero variance (two people at one spot) below 0
    placed = np.all(np.isfinite(x0), axis=1)
    return Measurements(x0, from_ankles & placed, frame_starts, first, second, pair_starts, dist, std)


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
    n = len(tops_px)
    m = measure_many(cal, tops_px, bottoms, [n], noise_px, height_std_m, height_scale, contact_std_fraction)
    placed = np.all(np.isfinite(m.points_bottom), axis=1)
    dist = np.diag(np.where(placed, 0.0, np.nan))
    std = np.zeros((n, n))
    for matrix, values in ((dist, m.distances_m), (std, m.distance_std_m)):
        matrix[m.first, m.second] = values
        matrix[m.second, m.first] = values
    return Measurement(m.points_bottom, m.from_ankles, dist, std)
