"""RANSAC over minimal samples (paper Sect. 3.4), vectorised across hypotheses.

A hypothesis is solved from 2 people (equal focal lengths or a known focal
length) or 3 (fx != fy) with the same batched linear steps as the batch solver,
then scored on every person at once. Inlier test, per person, for a hypothesis
(K, N, rho):

* direction: the Sampson distance of the segment from pointing at the vertical
  vanishing point K N is below ``inlier_px`` pixels. It is independent of the
  person's height, so it measures only keypoint noise and non-vertical bodies
  (bending, bad detections);
* height: the person placed on the hypothesised ground has an implied height
  within ``height_tolerance`` (relative) of the prior. This catches people whose
  direction is fine but whose scale is not: sitting people, people on stairs.

Once a winner exists, the keypoint noise is estimated from everyone's
direction residuals (median absolute deviation) and both tests are widened to
3 sigma of it, the height test per person by the relative error that noise
causes on that person's segment length; the refits use the widened tests.

Both residuals are combined into one MSAC cost c = (d/inlier_px)^2 +
((h/h0 - 1)/height_tolerance)^2, truncated at 1; an inlier has c < 1. The loop
stops adaptively once the best inlier ratio makes a better sample unlikely at
the requested confidence; the winner is refitted by the batch solver on its
inliers (twice, re-selecting inliers in between). Random draws come from the
caller's numpy Generator, so a seed makes the result deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .errors import CalibrationError
from .frame import FloatArray, homogeneous
from .linear import (
    LinearSolution,
    focal_weights,
    normal_and_rho,
    sampson_distances,
    scaled_depths,
    segment_lines,
    solve_linear,
)


@dataclass(frozen=True)
class RansacSettings:
    inlier_px: float
    height_tolerance: float = 0.2
    confidence: float = 0.999
    max_iterations: int = 5000
    batch: int = 128
    # Keypoint noise (px) once estimated: widens both tests so that noisy
    # detections (and the short segments of distant people) are not thrown out.
    noise_px: float = 0.0


@dataclass(frozen=True)
class RansacResult:
    solution: LinearSolution
    inliers: FloatArray
    iterations: int


def minimal_size(equal_focal: bool, focal_known: bool) -> int:
    return 2 if (equal_focal or focal_known) else 3


def _draw_samples(rng: np.random.Generator, n: int, m: int, count: int) -> FloatArray:
    """count rows of m distinct person indices."""
    samples = rng.integers(0, n, size=(count, m))
    for _ in range(100):
        s = np.sort(samples, axis=1)
        dup = np.any(s[:, 1:] == s[:, :-1], axis=1)
        if not dup.any():
            break
        samples[dup] = rng.integers(0, n, size=(int(dup.sum()), m))
    return samples


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


def score_hypotheses(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    focal: FloatArray,
    normal: FloatArray,
    rho: FloatArray,
    height_m: float,
    scale_px: float,
    settings: RansacSettings,
) -> FloatArray:
    """(M, N) truncated MSAC costs in [0, 1]; < 1 means inlier.

    Written out per component on (M, N) arrays: this is the hot loop of the
    robust solve, and reductions over a length-3 axis are several times slower.
    """
    tx, ty = tops_n[None, :, 0], tops_n[None, :, 1]
    bx, by = bottoms_n[None, :, 0], bottoms_n[None, :, 1]
    a, b = focal[:, :1], focal[:, 1:]
    n1, n2, n3 = normal[:, :1], normal[:, 1:2], normal[:, 2:]
    v1, v2, v3 = a * n1, b * n2, n3
    with np.errstate(invalid="ignore", divide="ignore"):
        # Sampson distance of the segment (t, b) from passing through v (see linear.sampson_distances).
        e = (ty - by) * v1 + (bx - tx) * v2 + (tx * by - ty * bx) * v3
        g2 = (by * v3 - v2) ** 2 + (v1 - bx * v3) ** 2 + (v2 - v3 * ty) ** 2 + (v3 * tx - v1) ** 2
        d_px = e / np.sqrt(g2) * scale_px
        # Height implied by placing the ankle on the plane (reconstruct.heights_above_ground, with N.X_B = -rho).
        ia2, ib2 = 1.0 / (a * a), 1.0 / (b * b)
        denom = n1 * bx / a + n2 * by / b + n3
        nr = n1 * tx / a + n2 * ty / b + n3
        rr = tx * tx * ia2 + ty * ty * ib2 + 1.0
        rx = -rho[:, None] * (tx * bx * ia2 + ty * by * ib2 + 1.0) / denom
        h = (rho[:, None] * rr + nr * rx) / (rr - nr * nr)
        inlier_px = max(settings.inlier_px, 3.0 * settings.noise_px)
        length_px = np.hypot(tx - bx, ty - by) * scale_px
        tolerance2 = settings.height_tolerance**2 + (3.0 * np.sqrt(2.0) * settings.noise_px / length_px) ** 2
        cost = (d_px / inlier_px) ** 2 + (h / height_m - 1.0) ** 2 / tolerance2
        cost = np.where((denom < 0) & np.isfinite(cost), cost, 1.0)
    return np.minimum(cost, 1.0)


def ransac(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    height_m: float,
    equal_focal: bool,
    focal_n: tuple[float, float] | None,
    scale_px: float,
    settings: RansacSettings,
    rng: np.random.Generator,
) -> RansacResult:
    n = len(tops_n)
    m = minimal_size(equal_focal, focal_n is not None)
    if n < m:
        raise CalibrationError(f"need at least {m} usable people, got {n}")
    tops_h, bottoms_h = homogeneous(tops_n), homogeneous(bottoms_n)
    best_cost, best_inliers = np.inf, np.zeros(n, bool)
    best: tuple[FloatArray, FloatArray, float] | None = None
    required, done = settings.max_iterations, 0
    while done < min(required, settings.max_iterations):
        count = min(settings.batch, settings.max_iterations - done)
        samples = _draw_samples(rng, n, m, count)
        focal, normal, rho, _ = solve_minimal(tops_h[samples], bottoms_h[samples], height_m, equal_focal, focal_n)
        ok = np.all(np.isfinite(focal), 1) & np.all(np.isfinite(normal), 1) & (rho > 0)
        done += count
        if not ok.any():
            continue
        focal, normal, rho = focal[ok], normal[ok], rho[ok]
        costs = score_hypotheses(tops_n, bottoms_n, focal, normal, rho, height_m, scale_px, settings)
        total = costs.sum(1)
        i = int(np.argmin(total))
        if total[i] < best_cost:
            best_cost, best_inliers = float(total[i]), costs[i] < 1.0
            best = (focal[i], normal[i], float(rho[i]))
            ratio = best_inliers.mean()
            required = _required_iterations(ratio, m, settings.confidence)
    if best is None or best_inliers.sum() < m:
        raise CalibrationError("no consistent group of upright people found (RANSAC found no valid hypothesis)")
    solution = LinearSolution((float(best[0][0]), float(best[0][1])), best[1], best[2])
    inliers = best_inliers
    v = solution.normal * np.array([solution.focal_n[0], solution.focal_n[1], 1.0])
    # Median absolute direction residual of everyone under the winner (robust while < 50 % are outliers).
    noise_px = 1.4826 * float(np.median(np.abs(sampson_distances(tops_h, bottoms_h, v)))) * scale_px
    settings = replace(settings, noise_px=noise_px)
    for round_ in range(2):
        try:
            refit = solve_linear(tops_n[inliers], bottoms_n[inliers], height_m, equal_focal, focal_n)
        except CalibrationError:
            if round_ == 0:
                raise  # the winning consensus set itself is degenerate: no trustworthy camera
            break
        costs = score_hypotheses(
            tops_n,
            bottoms_n,
            np.array([refit.focal_n]),
            refit.normal[None],
            np.array([refit.rho_m]),
            height_m,
            scale_px,
            settings,
        )[0]
        refit_inliers = costs < 1.0
        if refit_inliers.sum() < m:
            break
        solution, inliers = refit, refit_inliers
    return RansacResult(solution, inliers, done)


def _required_iterations(inlier_ratio: float, m: int, confidence: float) -> int:
    good = inlier_ratio**m
    if good >= 1.0:
        return 1
    if good <= 0.0:
        return 10**9
    return int(np.ceil(np.log(1.0 - confidence) / np.log(1.0 - good)))
