"""Estimating one-parameter division-model lens distortion (Fei et al. 2021, Appendix B; Fitzgibbon 2001).

Model (service.geometry.camera), in frame-normalised coordinates: the undistorted point is
u = u_d / (1 + k r_d^2) with r_d = |u_d|, so in homogeneous form
u~ ~ (u_d, 1 + k r_d^2) = u~_d + k z, z = (0, 0, r_d^2). Working in normalised
rather than pixel units keeps k of order 0.1 for real lenses instead of 1e-7.

Estimating k. Every constraint of Eq. 1 on k is a collinearity constraint:
with the two depths of a person eliminated in closed form, the residual of
lambda_T t~ - lambda_B b~ = h v is h (l.v)/|l| with l = t~ x b~, so the full
(2N+3)-unknown system of Appendix B carries exactly the information of the N
collinearity rows (L0_i + k L1_i).v = 0 (the k^2 term vanishes because
z_T x z_B = 0); formulations differ only in how they weight those rows. We therefore:

1. take seed roots from algebraic generalized eigenproblems: the paper's
   (A'^T A') X' = k (-A'^T C) X' (QZ, O(N^3), only for small crowds) and the
   3x3 collinearity pencil (M0^T W M0) v = k (-M0^T W M1) v (O(N));
2. add a coarse grid over the admissible k range (the algebraic roots are
   biased under noise and may all be complex);
3. polish every local minimum of the Sampson cost S(k) = min_v sum_i d_i^2,
   where d_i is the first-order distance, in *distorted* (measured)
   coordinates, by which person i's endpoints must move for its undistorted
   segment to point at v. Measuring in distorted units matters: the
   undistorted residual of a k > 0 model shrinks with k and would reward
   ever larger k;
4. keep k = 0 unless the best non-zero candidate lowers S by more than a
   chi^2_1 significance threshold in units of the residual variance: one
   extra parameter always lowers S, and a noise-fitted k costs more focal
   accuracy than a small unmodelled distortion. The threshold is the larger
   of the 99 % likelihood-ratio test's 6.6 and BIC's ln n: with thousands of
   people any small unmodelled effect (lean, keypoint bias) becomes
   "significant" at a fixed level, and BIC's penalty grows with the evidence.
   People seen in many frames count once (see `estimate_division_k`'s individuals).
   calibrate() then also asks the lens to matter (see `material`).

Monte-Carlo evaluation (20 people, 0.5 px noise, exact division-model scenes,
k in {-0.1, -0.05, 0, 0.05}): median |k error| 4e-3 to 6e-3 for the Sampson
polish against 3e-2 to 5e-2 for the algebraic roots even when an oracle picks
the root nearest the truth (the paper's and the 3x3 pencil's roots are equally
poor: they weight the same rows algebraically). The paper's problem is also
ill-conditioned exactly where real lenses live: at k = 0 its eigenvalue is
0/0 on exact data, because X'^T (-A'^T C) X' = -(A'X')^T C X' = 0.

Correction to the printed paper: in the last block row of A' the bottom column
must be -x~'_B,N, like every other row (C's -z_B is right); as printed, the
true k is not an eigenvalue even on exact data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike
from scipy.optimize import minimize_scalar

from .camera import lifted, undistort
from .errors import CalibrationError
from .linear import RANK_TOL
from .vec import FloatArray, cross, homogeneous

# |k| r_max^2 stays below this: at -1 the model maps the outermost points to
# infinity, at +1 it stops being monotone in the radius (two radii, one image).
DEFAULT_MAX_ABS_K_R2 = 0.8
# Keep a non-zero k only if it lowers the Sampson cost by more than this many
# residual variances (chi^2_1 at ~99 %; see the module docstring).
DEFAULT_SIGNIFICANCE_CHI2 = 6.6
# The paper's QZ problem is (2N+3)^2; beyond this many people it is skipped.
PAPER_MAX_PEOPLE = 60
_GRID_POINTS = 33
_IRLS_ITERATIONS = 3
_ROOT_IMAG_TOL = 1e-8


def paper_pencil(
    tops_n: FloatArray, bottoms_n: FloatArray, height_m: float, printed: bool = False
) -> tuple[FloatArray, FloatArray]:
    """(A', C) of Appendix B, unknowns X' = [lambda'_T1, lambda'_B1, ..., v]; printed=True keeps the typo.

    The typo (+x~'_B,N in the last block row) is kept available so the tests
    can show that it, unlike the corrected pencil, misses the true k.
    """
    n = len(tops_n)
    t, b = homogeneous(tops_n), homogeneous(bottoms_n)
    z_t, z_b = np.zeros((n, 3)), np.zeros((n, 3))
    z_t[:, 2], z_b[:, 2] = np.sum(tops_n**2, 1), np.sum(bottoms_n**2, 1)
    a = np.zeros((3 * n, 2 * n + 3))
    c = np.zeros((3 * n, 2 * n + 3))
    for i in range(n):
        rows = slice(3 * i, 3 * i + 3)
        a[rows, 2 * i], a[rows, 2 * i + 1] = t[i], -b[i]
        a[rows, 2 * n :] = -height_m * np.eye(3)
        c[rows, 2 * i], c[rows, 2 * i + 1] = z_t[i], -z_b[i]
    if printed and n:
        a[3 * n - 3 :, 2 * n - 1] = b[-1]
    return a, c


def paper_roots(tops_n: FloatArray, bottoms_n: FloatArray, height_m: float, printed: bool = False) -> FloatArray:
    """Real finite k of (A'^T A') X' = k (-A'^T C) X' by QZ, sorted; O(N^3), for small crowds and checks."""
    a, c = paper_pencil(tops_n, bottoms_n, height_m, printed)
    return _real_finite_eigenvalues(a.T @ a, -a.T @ c)


def collinearity_pencil(tops_n: FloatArray, bottoms_n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(L0, L1), each (N, 3): person i's undistorted image line is L0_i + k L1_i exactly."""
    t, b = homogeneous(tops_n), homogeneous(bottoms_n)
    z_t = np.zeros_like(t)
    z_b = np.zeros_like(b)
    z_t[:, 2], z_b[:, 2] = np.sum(tops_n**2, 1), np.sum(bottoms_n**2, 1)
    return np.cross(t, b), np.cross(z_t, b) + np.cross(t, z_b)


def collinearity_roots(tops_n: FloatArray, bottoms_n: FloatArray) -> FloatArray:
    """Real finite k of the 3x3 pencil (M0^T W M0) v = k (-M0^T W M1) v, rows weighted by 1/|L0_i|^2.

    The weight makes each row the depth-eliminated residual of Eq. 1 at k = 0
    (see the module docstring), so this is the O(N) stand-in for the paper's problem.
    """
    l0, l1 = collinearity_pencil(tops_n, bottoms_n)
    w = 1.0 / np.maximum(np.sum(l0 * l0, 1), 1e-300)
    return _real_finite_eigenvalues((l0 * w[:, None]).T @ l0, -(l0 * w[:, None]).T @ l1)


def _real_finite_eigenvalues(lhs: FloatArray, rhs: FloatArray) -> FloatArray:
    alpha_beta = scipy.linalg.eigvals(lhs, rhs, homogeneous_eigvals=True)
    alpha, beta = alpha_beta[0], alpha_beta[1]
    scale = np.maximum(np.abs(alpha), np.abs(beta))
    # alpha = beta = 0 marks a singular direction of the pencil (e.g. the true k = 0 of the paper's
    # problem on exact data: there X'^T (-A'^T C) X' = -(A'X')^T C X' = 0), not a root.
    determinate = scale > 1e-10 * max(float(np.max(np.abs(lhs))), float(np.max(np.abs(rhs))), 1e-300)
    finite = determinate & (np.abs(beta) > 1e-12 * np.maximum(scale, 1e-300))
    with np.errstate(divide="ignore", invalid="ignore"):
        k = alpha[finite] / beta[finite]
    real = np.isfinite(k) & (np.abs(k.imag) <= _ROOT_IMAG_TOL * np.maximum(1.0, np.abs(k.real)))
    return np.sort(k.real[real])


def sampson_cost(tops_n: FloatArray, bottoms_n: FloatArray, k: float | FloatArray) -> tuple[FloatArray, FloatArray]:
    """S(k) = min_v sum_i d_i^2 (normalised distorted units^2) and the minimising v, for each k.

    d_i is the Sampson distance of Eq. 2 with the gradient taken through the
    undistortion (d t~ / d u_d = [I; 2 k u_d^T]), so S is comparable across k.
    v is found by iteratively reweighted eigenvector fits, as in
    linear.vanishing_point. k broadcasts as (...,); returns S (...,) and v (..., 3).
    """
    kk = np.asarray(k, dtype=np.float64)
    t, b = lifted(tops_n, kk), lifted(bottoms_n, kk)
    lines = cross(t, b)
    weights = 1.0 / np.maximum(np.sum(lines * lines, -1), 1e-300)
    v = _weighted_null_vector(lines, weights)
    d = _sampson(tops_n, bottoms_n, t, b, v, kk)
    for _ in range(_IRLS_ITERATIONS):
        weights = np.where(d[1] > 0, 1.0 / np.maximum(d[1], 1e-300), 0.0)
        v = _weighted_null_vector(lines, weights)
        d = _sampson(tops_n, bottoms_n, t, b, v, kk)
    return np.sum(d[0] ** 2 / np.maximum(d[1], 1e-300), -1), v


def _weighted_null_vector(lines: FloatArray, weights: FloatArray) -> FloatArray:
    m = np.einsum("...n,...ni,...nj->...ij", weights, lines, lines)
    return np.linalg.eigh(m)[1][..., :, 0]


def _sampson(
    tops_n: FloatArray, bottoms_n: FloatArray, t: FloatArray, b: FloatArray, v: FloatArray, k: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(e, |grad e|^2) per person: algebraic residual and its squared gradient wrt the distorted endpoints.

    Written per component (e = (t x b).v, grad from b x v and v x t): the lens test evaluates it on every k of its
    grid for every person, and np.cross's temporaries were a tenth of a solve. Bit-identical to the vector form."""
    t0, t1, tw = t[..., 0], t[..., 1], t[..., 2]
    b0, b1, bw = b[..., 0], b[..., 1], b[..., 2]
    v0, v1, v2 = v[..., 0, None], v[..., 1, None], v[..., 2, None]
    e = (t1 * bw - tw * b1) * v0 + (tw * b0 - t0 * bw) * v1 + (t0 * b1 - t1 * b0) * v2
    bv2, vt2 = b0 * v1 - b1 * v0, v0 * t1 - v1 * t0
    kk = 2.0 * k[..., None]
    g_t0 = (b1 * v2 - bw * v1) + kk * tops_n[..., 0] * bv2
    g_t1 = (bw * v0 - b0 * v2) + kk * tops_n[..., 1] * bv2
    g_b0 = (v1 * tw - v2 * t1) + kk * bottoms_n[..., 0] * vt2
    g_b1 = (v2 * t0 - v0 * tw) + kk * bottoms_n[..., 1] * vt2
    return e, (g_t0 * g_t0 + g_t1 * g_t1) + (g_b0 * g_b0 + g_b1 * g_b1)


@dataclass(frozen=True)
class DivisionEstimate:
    """The chosen k (normalised units) and the evidence: every candidate with its Sampson cost."""

    k: float
    candidates_k: tuple[float, ...]
    costs: tuple[float, ...]
    k_bounds: tuple[float, float]
    reason: str


def estimate_division_k(
    tops_n: ArrayLike,
    bottoms_n: ArrayLike,
    height_m: float = 1.0,
    *,
    max_abs_k_r2: float = DEFAULT_MAX_ABS_K_R2,
    radius_max_n: float | None = None,
    significance_chi2: float = DEFAULT_SIGNIFICANCE_CHI2,
    individuals: ArrayLike | None = None,
) -> DivisionEstimate:
    """Division-model k from people's distorted normalised points (see the module docstring for the method).

    height_m only scales v in the paper's pencil and cannot change k.
    individuals, optional, labels each observation with the person it is (service.geometry.tracks). One
    person's residuals are not independent (their lean and the pose model's error on their body persist from
    frame to frame), so the significance test counts individuals: the cost drop is deflated by the design
    effect of the residuals' clustering (`_design_effect`: up to sum(m_i^2) / n for clusters of m_i
    observations whose residuals are one person's constant), and BIC's penalty is ln(individuals). Counted
    as observations, 240 frames of 36 walkers chose a spurious k on 2 of 6 distortion-free streets (f 2-3 %
    short).
    radius_max_n (e.g. the image corner radius) sets the admissible range
    |k| <= max_abs_k_r2 / radius_max_n^2; by default the outermost keypoint.
    """
    tops, bottoms = np.asarray(tops_n, dtype=np.float64), np.asarray(bottoms_n, dtype=np.float64)
    if tops.ndim != 2 or tops.shape[1] != 2 or tops.shape != bottoms.shape:
        raise CalibrationError(f"tops and bottoms must be two (N, 2) arrays, got {tops.shape} and {bottoms.shape}")
    n = len(tops)
    if n < 3:
        raise CalibrationError(f"estimating lens distortion needs at least 3 people, got {n}")
    if not (np.all(np.isfinite(tops)) and np.all(np.isfinite(bottoms))):
        raise CalibrationError("keypoints must be finite")
    length = np.linalg.norm(tops - bottoms, axis=1)
    if not np.all(length > 1e-12 * max(1.0, float(np.max(np.abs(tops))))):
        raise CalibrationError("a person's ankle and shoulder centres coincide (zero-length segment)")
    _check_lines(tops, bottoms)
    r_max = float(np.sqrt(max(np.max(np.sum(tops**2, 1)), np.max(np.sum(bottoms**2, 1)))))
    r_max = r_max if radius_max_n is None else max(r_max, float(radius_max_n))
    k_max = max_abs_k_r2 / max(r_max * r_max, 1e-300)

    grid = np.linspace(-k_max, k_max, _GRID_POINTS)
    grid_cost = sampson_cost(tops, bottoms, grid)[0]
    scale = float(np.max(grid_cost))
    if scale <= 1e-24 * n or np.ptp(grid_cost) <= 1e-9 * scale:
        raise CalibrationError(
            "lens distortion is not observable from these people (e.g. every segment points at the image centre)"
        )
    seeds = [collinearity_roots(tops, bottoms)]
    if n <= PAPER_MAX_PEOPLE:
        seeds.append(paper_roots(tops, bottoms, height_m))
    algebraic = np.concatenate(seeds)
    algebraic = algebraic[np.abs(algebraic) <= k_max]
    polished = [_polish(tops, bottoms, grid, grid_cost, i) for i in _local_minima(grid_cost)]
    candidates = np.unique(np.concatenate(([0.0], algebraic, polished)))
    costs = sampson_cost(tops, bottoms, candidates)[0]
    zero = int(np.flatnonzero(candidates == 0.0)[0])
    best = int(np.argmin(np.where(candidates == 0.0, np.inf, costs))) if len(candidates) > 1 else zero
    dof = n - 3
    groups, design_effect = _design_effect(tops, bottoms, float(candidates[zero]), individuals)
    if best == zero:
        k, reason = 0.0, "no admissible non-zero candidate"
    elif dof == 0:
        k, reason = float(candidates[best]), "3 people determine k exactly; no redundancy to test it"
    elif (costs[zero] - costs[best]) / design_effect > max(significance_chi2, np.log(groups)) * costs[best] / dof:
        k, reason = float(candidates[best]), "lowest Sampson cost, significantly below k = 0"
    else:
        k, reason = 0.0, "no candidate lowers the Sampson cost significantly below k = 0"
    return DivisionEstimate(k, tuple(candidates.tolist()), tuple(costs.tolist()), (-k_max, k_max), reason)


def _design_effect(
    tops_n: FloatArray, bottoms_n: FloatArray, k: float, individuals: ArrayLike | None
) -> tuple[int, float]:
    """(individuals, the design effect 1 + (m_w - 1) rho of the Sampson residuals at k).

    m_w = sum(m_i^2) / n is the size-weighted mean number of observations per individual, rho the residuals'
    intra-individual correlation (one-way ANOVA estimator, clipped to [0, 1]): 1 when each observation is its
    own individual or one person's residuals vary from frame to frame as much as people's do, m_w when they
    are one person's constant.
    """
    n = len(tops_n)
    if individuals is None:
        return n, 1.0
    labels = np.asarray(individuals).reshape(-1)
    if labels.shape != (n,):
        raise CalibrationError(f"individuals must hold one label per person ({n}), got shape {labels.shape}")
    index, sizes = np.unique(labels, return_inverse=True, return_counts=True)[1:]
    groups = len(sizes)
    if groups < 2 or groups == n:
        return groups, 1.0
    kk = np.asarray(k, dtype=np.float64)
    t, b = lifted(tops_n, kk), lifted(bottoms_n, kk)
    v = sampson_cost(tops_n, bottoms_n, k)[1]
    e, gradient2 = _sampson(tops_n, bottoms_n, t, b, v, kk)
    residual = e / np.sqrt(np.maximum(gradient2, 1e-300))
    means = np.bincount(index, residual) / sizes
    within = float(np.sum((residual - means[index]) ** 2)) / (n - groups)
    between = float(np.sum(sizes * (means - residual.mean()) ** 2)) / (groups - 1)
    weighted = float(np.sum(sizes.astype(np.float64) ** 2) / n)
    m0 = (n - weighted) / (groups - 1)
    rho = (between - within) / max(between + (m0 - 1.0) * within, 1e-300)
    return groups, 1.0 + (weighted - 1.0) * float(np.clip(rho, 0.0, 1.0))


def corner_shift_n(k: float, radius_max_n: float) -> float:
    """How far (normalised units) the division model moves a point at radius radius_max_n."""
    return abs(radius_max_n - float(undistort(np.array([[radius_max_n, 0.0]]), k)[0, 0]))


def _check_lines(tops: FloatArray, bottoms: FloatArray) -> None:
    lines = np.cross(homogeneous(tops), homogeneous(bottoms))
    lines /= np.linalg.norm(lines, axis=1, keepdims=True)
    s = np.linalg.svd(lines, compute_uv=False)
    if s[1] <= RANK_TOL * s[0]:
        raise CalibrationError("every person lies on one image line: no vanishing point, no distortion")


def _local_minima(cost: FloatArray) -> list[int]:
    inner = [i for i in range(1, len(cost) - 1) if cost[i] <= cost[i - 1] and cost[i] <= cost[i + 1]]
    edges = [i for i in (0, len(cost) - 1) if cost[i] == np.min(cost)]
    return inner + edges


def _polish(tops: FloatArray, bottoms: FloatArray, grid: FloatArray, cost: FloatArray, i: int) -> float:
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    step = float(grid[1] - grid[0])
    found = minimize_scalar(
        lambda k: float(sampson_cost(tops, bottoms, k)[0]),
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 1e-6 * step},
    )
    return float(found.x) if found.fun <= cost[i] else float(grid[i])
