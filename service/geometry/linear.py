"""Direct linear solver (Fei et al. 2021, Sect. 3.2-3.3) in normalised coordinates.

Three linear steps: the vertical vanishing point v = K N from the
collinearity of every segment with v (Eq. 2), per-person depths up to one
common scale (Eq. 1), and W = diag(1/fx^2, 1/fy^2, 1) from the requirement
that all ankle centres lie on one plane orthogonal to N (Eq. 3).

Corrections to the printed paper, each checked on exact synthetic scenes by
the unit tests: the scale is mu = +-sqrt(v~' W v~) (the paper drops the square
root); the right-hand side of [B|y] is y = -v~_3 d_3; and the N(N-1)/2 pairwise
rows of Eq. 3 are replaced by the N centred rows (d_i - mean d), which give the
same least-squares solution in O(N).

Steps after the vanishing point are written over a leading batch axis so the
same code serves the batch solve (one problem, all people) and RANSAC (many
minimal problems at once); they report invalid problems as NaN instead of raising.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import CalibrationError
from .vec import FloatArray, cross, dot, homogeneous

# Relative size below which a singular value or determinant counts as zero.
RANK_TOL = 1e-10


@dataclass(frozen=True)
class LinearSolution:
    """Camera in normalised units: focal_n = (fx, fy) / frame scale."""

    focal_n: tuple[float, float]
    normal: FloatArray
    rho_m: float


def segment_lines(tops_h: FloatArray, bottoms_h: FloatArray) -> FloatArray:
    """Homogeneous image line through each person's two points."""
    return cross(tops_h, bottoms_h)


def sampson_distances(tops_h: FloatArray, bottoms_h: FloatArray, v: FloatArray) -> FloatArray:
    """First-order geometric distance (normalised units) of each segment from pointing at v.

    It is the smallest displacement of the two endpoints that makes them
    collinear with v: a height-independent residual, so it measures keypoint
    noise alone. v broadcasts against the points: (3,) or (M, 1, 3).
    """
    e = dot(segment_lines(tops_h, bottoms_h), v)
    # The first two components of b x v and v x t (the gradient wrt the endpoints' pixels), written out: the
    # consensus scores every hypothesis against every person with this.
    t0, t1, t2 = tops_h[..., 0], tops_h[..., 1], tops_h[..., 2]
    b0, b1, b2 = bottoms_h[..., 0], bottoms_h[..., 1], bottoms_h[..., 2]
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    g_top_0, g_top_1 = b1 * v2 - b2 * v1, b2 * v0 - b0 * v2
    g_bottom_0, g_bottom_1 = v1 * t2 - v2 * t1, v2 * t0 - v0 * t2
    denom = np.sqrt(g_top_0**2 + g_top_1**2 + g_bottom_0**2 + g_bottom_1**2)
    return e / np.maximum(denom, 1e-300)


def vanishing_point(tops_h: FloatArray, bottoms_h: FloatArray, irls_iterations: int = 2) -> FloatArray:
    """Least-squares v (unit 3-vector, sign arbitrary) with Sampson-reweighted rows.

    Plain algebraic rows weight a person by segment length times distance to v;
    reweighting by the Sampson gradient turns that into pixel-noise units, which
    matters when v is close to the image (steep views).
    """
    lines = segment_lines(tops_h, bottoms_h)
    weights = 1.0 / dot(lines, lines)
    for _ in range(irls_iterations):
        # The 3x3 normal equations are cheap and accurate enough for the weights...
        v = np.linalg.eigh((lines * weights[:, None]).T @ lines)[1][:, 0]
        g_top = cross(bottoms_h, v)
        g_bottom = cross(v, tops_h)
        denom = g_top[:, 0] ** 2 + g_top[:, 1] ** 2 + g_bottom[:, 0] ** 2 + g_bottom[:, 1] ** 2
        weights = 1.0 / np.maximum(denom, 1e-12 * np.max(denom))
    # ... but the answer comes from an SVD of the rows: the normal equations square
    # the condition number and cost digits on exact, nearly degenerate input.
    _, sv, vt = np.linalg.svd(lines * np.sqrt(weights)[:, None], full_matrices=len(lines) < 3)
    if len(sv) < 2 or sv[1] <= np.sqrt(RANK_TOL) * sv[0]:
        raise CalibrationError(
            "the segments do not determine a vanishing point: fewer than two distinct lines "
            "(e.g. every person on one image line)"
        )
    return vt[2]


def scaled_depths(
    tops_h: FloatArray, bottoms_h: FloatArray, v: FloatArray, height_m: float
) -> tuple[FloatArray, FloatArray]:
    """Least-squares (lambda_T, lambda_B) of Eq. 1 per person, up to the common scale mu.

    Shapes (..., n, 3) for the points and (..., 1, 3) for v.
    """
    tt = dot(tops_h, tops_h)
    bb = dot(bottoms_h, bottoms_h)
    tb = dot(tops_h, bottoms_h)
    tv = dot(tops_h, v)
    bv = dot(bottoms_h, v)
    det = tt * bb - tb * tb
    with np.errstate(divide="ignore", invalid="ignore"):
        det = np.where(det > RANK_TOL * tt * bb, det, np.nan)
        return height_m * (bb * tv - tb * bv) / det, height_m * (tb * tv - tt * bv) / det


def focal_weights(bottoms_h: FloatArray, lam_b: FloatArray, v: FloatArray, equal_focal: bool) -> FloatArray:
    """(..., 2) array of (1/fx^2, 1/fy^2) from the centred ground-plane rows of Eq. 3; NaN if undetermined."""
    p = bottoms_h * lam_b[..., None]
    d = p - p.mean(axis=-2, keepdims=True)
    y = -v[..., 2] * d[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        if equal_focal:
            b = v[..., 0] * d[..., 0] + v[..., 1] * d[..., 1]
            bb = np.sum(b * b, -1)
            w = np.where(bb > RANK_TOL * np.sum(y * y, -1), np.sum(b * y, -1) / bb, np.nan)
            return np.stack((w, w), -1)
        b0, b1 = v[..., 0] * d[..., 0], v[..., 1] * d[..., 1]
        m00, m01, m11 = np.sum(b0 * b0, -1), np.sum(b0 * b1, -1), np.sum(b1 * b1, -1)
        r0, r1 = np.sum(b0 * y, -1), np.sum(b1 * y, -1)
        det = m00 * m11 - m01 * m01
        yy = RANK_TOL * np.sum(y * y, -1)
        det = np.where((det > RANK_TOL * m00 * m11) & (m00 > yy) & (m11 > yy), det, np.nan)
        return np.stack(((m11 * r0 - m01 * r1) / det, (m00 * r1 - m01 * r0) / det), -1)


def normal_and_rho(
    tops_h: FloatArray,
    bottoms_h: FloatArray,
    v: FloatArray,
    lam_t: FloatArray,
    lam_b: FloatArray,
    focal_n: FloatArray,
    height_m: float,
) -> tuple[FloatArray, FloatArray]:
    """Unit up-normal (..., 3) and rho (...) once the focal lengths are known.

    mu = +-|K^-1 v~| with the sign that puts the people in front of the camera;
    rho averages the plane through the ankles and the plane h above it (Sect. 3.3).
    """
    k_inv = np.concatenate((1.0 / focal_n, np.ones(focal_n.shape[:-1] + (1,))), -1)
    k_inv_v = v[..., 0, :] * k_inv
    sign = np.sign(np.median(lam_b, axis=-1))
    mu = np.linalg.norm(k_inv_v, axis=-1) * np.where(sign == 0, 1.0, sign)
    normal = k_inv_v / mu[..., None]
    rays_b = bottoms_h * k_inv[..., None, :]
    rays_t = tops_h * k_inv[..., None, :]
    x_b = rays_b * (lam_b / mu[..., None])[..., None]
    x_t = rays_t * (lam_t / mu[..., None])[..., None]
    centroid = 0.5 * (x_b.mean(-2) + x_t.mean(-2))
    rho = 0.5 * height_m - dot(normal, centroid)
    return normal, rho


def solve_linear(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    height_m: float,
    equal_focal: bool = True,
    focal_n: tuple[float, float] | None = None,
) -> LinearSolution:
    """Batch solve of K (unless focal_n is given), N and rho from normalised points."""
    tops_h, bottoms_h = homogeneous(tops_n), homogeneous(bottoms_n)
    minimum = 2 if (equal_focal or focal_n is not None) else 3
    if len(tops_h) < minimum:
        raise CalibrationError(f"need at least {minimum} usable people, got {len(tops_h)}")
    v = vanishing_point(tops_h, bottoms_h)[None, :]
    lam_t, lam_b = scaled_depths(tops_h, bottoms_h, v, height_m)
    if not np.all(np.isfinite(lam_b)):
        raise CalibrationError("a person's ankle and shoulder centres coincide (zero-length segment)")
    if focal_n is None:
        w = focal_weights(bottoms_h, lam_b, v, equal_focal)
        if not np.all(np.isfinite(w)):
            raise CalibrationError(
                "the ground-plane constraints do not determine the focal length"
                + ("" if equal_focal else " (fx and fy cannot be told apart without camera roll; use equal_focal)")
            )
        if not np.all(w > 0):
            raise CalibrationError("the ground-plane constraints give a non-positive 1/f^2: no real focal length fits")
        focal = 1.0 / np.sqrt(w)
    else:
        focal = np.asarray(focal_n, dtype=np.float64)
    normal, rho = normal_and_rho(tops_h, bottoms_h, v, lam_t, lam_b, focal, height_m)
    if not rho > 0:
        raise CalibrationError("the fitted ground plane is not below the camera (rho <= 0)")
    return LinearSolution((float(focal[0]), float(focal[1])), normal, float(rho))
