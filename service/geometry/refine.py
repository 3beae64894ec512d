"""Maximum a posteriori fit of the camera, its nuisances and every person (service.geometry.model).

The linear solver minimises algebraic errors, treats every person as exactly h tall and assumes the
principal point, square pixels and an unbiased pose model. Here the camera parameters theta (with priors on
what people cannot determine), each observation's latent ankle and each individual's latent height are
chosen to minimise the whitened residuals of the generative model plus the priors: the statistically
efficient estimate when the model holds, and its Gauss-Newton covariance carries the priors' spread into
theta.

Levenberg-Marquardt with the structure of bundle adjustment: the normal equations are arrow-shaped, so
each step eliminates the observations' 2x2 ankle blocks, then each individual's height (one scalar per
individual, summed over its observations), and solves the small reduced system in theta (the Schur
complement). The same complement, undamped, is the inverse of theta's marginal covariance. Every step
costs O(n p^2) for n observations and p camera parameters; Jacobians are central differences, evaluated for
all observations and all perturbed cameras in two vectorised passes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import CameraBatch, Layout, Observations, Priors, unpack
from .vec import FloatArray

_MAX_ITERATIONS = 60
_CONVERGED_DECREMENT = 1e-16
_STEP_THETA = 1e-5
_STEP_PERSON = 1e-5


@dataclass(frozen=True)
class MapProblem:
    """Everything fixed during one fit."""

    layout: Layout
    priors: Priors
    observations: Observations
    normal0: FloatArray
    mu0: float

    def cameras(self, theta: FloatArray) -> CameraBatch:
        return unpack(self.layout, np.atleast_2d(theta), self.normal0, self.mu0)


@dataclass(frozen=True)
class MapFit:
    theta: FloatArray
    covariance: FloatArray  # of theta (p x p): the posterior's Gauss-Newton covariance
    ankles_n: FloatArray  # (n, 2) latent ankle keypoints (distorted, noise-free)
    deviations: FloatArray  # (T,) each individual's height relative to the mean, h = mu (1 + deviation)
    person_costs: FloatArray  # (n,) each observation's squared whitened data residuals
    data_cost: float  # sum of squared whitened data residuals (without the priors)
    variance_factor: float  # data residuals' mean square per degree of freedom
    iterations: int


def _inv2(m: FloatArray) -> FloatArray:
    """Batched inverse of 2x2 matrices (a zero inverse for a singular block: a person with no information)."""
    a, b, c, d = m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1]
    det = a * d - b * c
    scale = np.maximum(np.abs(a * d), 1e-300)
    inv_det = np.where(np.abs(det) > 1e-14 * scale, 1.0 / np.where(det == 0, 1.0, det), 0.0)
    out = np.empty_like(m)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = d, -b, -c, a
    return out * inv_det[:, None, None]


@dataclass
class _Linearisation:
    r: FloatArray  # (n, 4) data residuals
    j_theta: FloatArray  # (n, 4, p)
    j_ankle: FloatArray  # (n, 4, 2)
    j_height: FloatArray  # (n, 4)


def _linearise(problem: MapProblem, theta: FloatArray, ankles: FloatArray, heights: FloatArray) -> _Linearisation:
    """Residuals and central-difference Jacobians; `heights` are the individuals' relative deviations.

    Central differences (truncation error ~1e-10) make the fit converge to the same digits whatever the
    image's scale or the people's order: forward differences left ~1e-6 of the posterior's flat directions
    to floating-point luck.
    """
    obs = problem.observations
    h_obs = heights[obs.track]
    p = len(theta)
    steps = _STEP_THETA * np.maximum(1.0, np.abs(theta))
    thetas = np.vstack((theta, theta + np.diag(steps), theta - np.diag(steps)))
    res = obs.residuals(problem.cameras(thetas), ankles, h_obs)  # (2p + 1, n, 4)
    base = res[0]
    j_theta = np.moveaxis((res[1 : p + 1] - res[p + 1 :]) / (2.0 * steps[:, None, None]), 0, -1)
    step_a = _STEP_PERSON * np.maximum(1.0, np.abs(ankles))
    moved = np.stack([ankles] * 6)
    moved[0, :, 0] += step_a[:, 0]
    moved[1, :, 0] -= step_a[:, 0]
    moved[2, :, 1] += step_a[:, 1]
    moved[3, :, 1] -= step_a[:, 1]
    step_h = _STEP_PERSON * np.maximum(1.0, np.abs(h_obs))
    h_moved = np.stack((h_obs, h_obs, h_obs, h_obs, h_obs + step_h, h_obs - step_h))
    person = obs.residuals(problem.cameras(np.vstack([theta] * 6)), moved, h_moved)
    j_ankle = np.stack(
        ((person[0] - person[1]) / (2.0 * step_a[:, :1]), (person[2] - person[3]) / (2.0 * step_a[:, 1:])), -1
    )
    j_height = (person[4] - person[5]) / (2.0 * step_h[:, None])
    return _Linearisation(base, j_theta, j_ankle, j_height)


def _prior_terms(problem: MapProblem, theta: FloatArray, heights: FloatArray) -> tuple[FloatArray, ...]:
    """Residuals of the priors and their Jacobians: on theta (p,), on the individuals' deviations (T,), and
    the camera-height residual with its log_rho derivative."""
    layout, priors = problem.layout, problem.priors
    finite = np.isfinite(layout.prior_std)
    r_theta = np.where(finite, theta / np.where(finite, layout.prior_std, 1.0), 0.0)
    r_height = heights / priors.height_std_rel
    r_cam, d_cam = np.zeros(0), np.zeros(0)
    if priors.camera_height_m is not None:
        rho = float(np.exp(layout.value(theta[None], "log_rho")[0]))
        known, std = priors.camera_height_m
        r_cam, d_cam = np.array([(rho - known) / std]), np.array([rho / std])
    return r_theta, r_height, r_cam, d_cam


def _cost(problem: MapProblem, theta: FloatArray, ankles: FloatArray, heights: FloatArray) -> tuple[float, FloatArray]:
    obs = problem.observations
    r = obs.residuals(problem.cameras(theta), ankles, heights[obs.track])[0]
    priors = _prior_terms(problem, theta, heights)
    total = float(np.sum(r * r) + sum(np.sum(x * x) for x in (priors[0], priors[1], priors[2])))
    return total, r


@dataclass
class _Reduced:
    s: FloatArray  # (p, p) Schur complement on theta
    g: FloatArray  # (p,)
    # Back-substitution pieces.
    x: FloatArray
    y: FloatArray
    z: FloatArray
    h_hh: FloatArray
    h_htheta: FloatArray
    g_h: FloatArray


def _reduce(
    problem: MapProblem, lin: _Linearisation, theta: FloatArray, heights: FloatArray, damping: float
) -> _Reduced:
    obs, layout = problem.observations, problem.layout
    ja, jh, jt, r = lin.j_ankle, lin.j_height, lin.j_theta, lin.r
    p = len(theta)
    ja_t = np.swapaxes(ja, 1, 2)
    u_aa = ja_t @ ja
    u_ah = (ja_t @ jh[:, :, None])[:, :, 0]
    u_hh = np.sum(jh * jh, 1)
    w_at = ja_t @ jt
    w_ht = (jh[:, None, :] @ jt)[:, 0, :]
    flat = jt.reshape(-1, p)
    v_tt = flat.T @ flat
    g_a = (ja_t @ r[:, :, None])[:, :, 0]
    g_h = np.sum(jh * r, 1)
    g_t = flat.T @ r.ravel()

    r_theta, r_height, r_cam, d_cam = _prior_terms(problem, theta, heights)
    finite = np.isfinite(layout.prior_std)
    inv_std = np.where(finite, 1.0 / np.where(finite, layout.prior_std, 1.0), 0.0)
    v_tt = v_tt + np.diag(inv_std**2)
    g_t = g_t + inv_std * r_theta
    inv_h = 1.0 / problem.priors.height_std_rel
    t_count = obs.tracks
    h_prior_hh = np.full(t_count, inv_h**2)
    h_prior_g = inv_h * r_height
    if len(r_cam):
        i = layout.index["log_rho"]
        v_tt[i, i] += float(d_cam[0] ** 2)
        g_t[i] += float(d_cam[0] * r_cam[0])

    # Marquardt damping on every diagonal.
    u_aa = u_aa + damping * np.einsum("nii->ni", u_aa)[:, :, None] * np.eye(2)
    v_tt = v_tt + damping * np.diag(np.diag(v_tt))
    u_inv = _inv2(u_aa)
    x = u_inv @ w_at  # (n, 2, p)
    y = (u_inv @ u_ah[:, :, None])[:, :, 0]
    z = (u_inv @ g_a[:, :, None])[:, :, 0]
    hh_o = u_hh - np.sum(u_ah * y, 1)
    ht_o = w_ht - (u_ah[:, None, :] @ x)[:, 0, :]
    gh_o = g_h - np.sum(u_ah * z, 1)
    h_hh = (np.bincount(obs.track, hh_o, t_count) + h_prior_hh) * (1.0 + damping)
    h_ht = np.zeros((t_count, p))
    np.add.at(h_ht, obs.track, ht_o)
    gh_t = np.bincount(obs.track, gh_o, t_count) + h_prior_g
    w_flat = w_at.reshape(-1, p)
    s = v_tt - w_flat.T @ x.reshape(-1, p) - (h_ht / h_hh[:, None]).T @ h_ht
    g = g_t - w_flat.T @ z.ravel() - h_ht.T @ (gh_t / h_hh)
    return _Reduced(s, g, x, y, z, h_hh, h_ht, gh_t)


def _step(
    problem: MapProblem,
    red: _Reduced,
    ankles: FloatArray,
    heights: FloatArray,
    theta: FloatArray,
    frozen: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One Gauss-Newton step from the reduced system; frozen keeps theta and moves only the people."""
    d_theta = np.zeros(len(theta))
    free = problem.layout.estimated
    if not frozen and free.any():
        d_theta[free] = np.linalg.lstsq(red.s[np.ix_(free, free)], -red.g[free], rcond=None)[0]
    d_h = -(red.g_h + red.h_htheta @ d_theta) / red.h_hh
    track = problem.observations.track
    d_a = -(red.z + red.y * d_h[track][:, None] + red.x @ d_theta)
    lower, upper = problem.layout.bounds()
    # Deviations beyond -0.9 would be people of a tenth of the height: the prior already says no.
    return np.clip(theta + d_theta, lower, upper), ankles + d_a, np.clip(heights + d_h, -0.9, 2.0)


def _consider_covariance(layout: Layout, s: FloatArray) -> FloatArray:
    """Covariance of theta when the considered parameters c are held at 0 rather than estimated.

    With A = S_ee (the estimated block, priors included), B = S_ec (cross terms: data only) and P the
    considered parameters' prior covariance, holding c at 0 while its truth is c* shifts the estimate by
    M c*, M = A^-1 B; so cov(e) = A^-1 + M P M^T, cov(e, c) = -M P, cov(c) = P.
    """
    if not len(s):
        return np.zeros((0, 0))
    e = layout.estimated
    if e.all():
        return np.linalg.pinv(s, hermitian=True)
    c = ~e
    a_inv = np.linalg.pinv(s[np.ix_(e, e)], hermitian=True)
    m = a_inv @ s[np.ix_(e, c)]
    p = np.diag(layout.prior_std[c] ** 2)
    cov = np.zeros_like(s)
    cov[np.ix_(e, e)] = a_inv + m @ p @ m.T
    cov[np.ix_(e, c)] = -m @ p
    cov[np.ix_(c, e)] = (-m @ p).T
    cov[np.ix_(c, c)] = p
    return cov


def fit_map(
    problem: MapProblem,
    theta0: FloatArray,
    heights0: FloatArray,
    *,
    optimise: bool = True,
    ankles: FloatArray | None = None,
) -> MapFit:
    """Levenberg-Marquardt from theta0 (latent ankles start at the measured ones unless given, heights at
    heights0); optimise=False only evaluates the covariance there."""
    obs = problem.observations
    theta, heights = theta0.astype(np.float64), heights0.astype(np.float64)
    ankles = obs.bottoms_n.copy() if ankles is None else ankles.copy()
    # optimise=False: people still take their best positions and heights for this camera (theta frozen).
    cost, _ = _cost(problem, theta, ankles, heights)
    damping = 1e-4
    iterations = 0
    for iterations in range(1, _MAX_ITERATIONS + 1):  # noqa: B007 - the count is reported
        lin = _linearise(problem, theta, ankles, heights)
        converged = True
        for _ in range(12):
            red = _reduce(problem, lin, theta, heights, damping)
            candidate = _step(problem, red, ankles, heights, theta, frozen=not optimise)
            new_cost, _ = _cost(problem, *candidate)
            if np.isfinite(new_cost) and new_cost <= cost:
                # Converged once the step is far below the parameters' own uncertainty (the Newton
                # decrement in units of the posterior: 1e-16 is a step of 1e-8 sigma) and the people's
                # steps are as small, or when no step lowers the cost (floating-point noise).
                d = candidate[0] - theta
                decrement = float(d @ red.s @ d) + float(np.sum((candidate[2] - heights) ** 2 * red.h_hh))
                theta, ankles, heights = candidate
                cost = new_cost
                damping = max(damping / 5.0, 1e-9)
                converged = decrement < _CONVERGED_DECREMENT
                break
            damping *= 8.0
        if converged:
            break
    lin = _linearise(problem, theta, ankles, heights)
    red = _reduce(problem, lin, theta, heights, 0.0)
    covariance = _consider_covariance(problem.layout, red.s)
    person = np.sum(lin.r * lin.r, axis=1)
    data_cost = float(np.sum(person))
    dof = max(2 * len(person) - len(theta), 1)
    r_height = _prior_terms(problem, theta, heights)[1]
    return MapFit(
        theta=theta,
        covariance=covariance,
        ankles_n=ankles,
        deviations=heights,
        person_costs=person,
        data_cost=data_cost,
        variance_factor=(data_cost + float(np.sum(r_height**2))) / dof,
        iterations=iterations,
    )
