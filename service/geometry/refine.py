"""Maximum a posteriori fit of the camera, its nuisances and every person (service.geometry.model).

The linear solver minimises algebraic errors, treats every person as exactly h tall and assumes the
principal point, square pixels and an unbiased pose model. Here the camera parameters theta (with priors on
what people cannot determine), each observation's latent ankle and each individual's latent height (and
lean) are chosen to minimise the whitened residuals of the generative model plus the priors: the
statistically efficient estimate when the model holds, and its Gauss-Newton covariance carries the priors'
spread into theta.

Levenberg-Marquardt with the structure of bundle adjustment: the normal equations are arrow-shaped, so
each step eliminates the observations' 2x2 ankle blocks, then each individual's q x q block (q = 1: the
height; q = 2: height and lean, summed over the individual's observations), and solves the small reduced
system in theta (the Schur complement). The same complement, undamped, is the inverse of theta's marginal
covariance. Every step costs O(n p^2) for n observations and p camera parameters; the Jacobians are exact
(model.residuals_and_jacobians: one pass through the model and its chain rule, vectorised over observations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import CameraBatch, Layout, Linearisation, Observations, Priors, residuals_and_jacobians, unpack
from .vec import FloatArray

_MAX_ITERATIONS = 60
# Converged once a step is 1e-3 of the posterior's sigma (the Newton decrement is its square). Against a 1e-8-sigma
# test, on 12 realistic-simulator cameras of 2 000 observations: f moves by at most 5e-5 relative (~2e-3 of its
# sigma), the normal by 2e-5 rad, and half the iterations go (9.2 -> 4.8 per fit, 77 -> 55 ms of CPU per solve).
_CONVERGED_DECREMENT = 1e-6


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
    person: FloatArray  # (T, q) each individual's height deviation (h = mu (1 + deviation)) [and lean, rad]
    person_costs: FloatArray  # (n,) each observation's squared whitened residuals and its share of its prior
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


def _linearise(problem: MapProblem, theta: FloatArray, ankles: FloatArray, person: FloatArray) -> Linearisation:
    """Residuals and their exact Jacobians; `person` holds the individuals' (T, q) parameters.

    Exact rather than differenced: the fit converges to the same digits whatever the image's scale or the
    people's order (forward differences left ~1e-6 of the posterior's flat directions to floating-point luck,
    central ones cost 2 (p + 2 + q) + 1 evaluations of the model per linearisation).
    """
    obs = problem.observations
    return residuals_and_jacobians(problem.layout, theta, problem.normal0, problem.mu0, obs, ankles, person[obs.track])


def _person_prior_std(problem: MapProblem, q: int) -> FloatArray:
    priors = problem.priors
    return np.array([priors.height_std_rel, priors.lean_rad][:q])


def _prior_terms(problem: MapProblem, theta: FloatArray, person: FloatArray) -> tuple[FloatArray, ...]:
    """Residuals of the priors and their Jacobians: on theta (p,), on the individuals (T, q), and the
    camera-height residual with its log_rho derivative."""
    layout, priors = problem.layout, problem.priors
    finite = np.isfinite(layout.prior_std)
    r_theta = np.where(finite, theta / np.where(finite, layout.prior_std, 1.0), 0.0)
    r_person = person / _person_prior_std(problem, person.shape[1])
    r_cam, d_cam = np.zeros(0), np.zeros(0)
    if priors.camera_height_m is not None:
        rho = float(np.exp(layout.value(theta[None], "log_rho")[0]))
        known, std = priors.camera_height_m
        r_cam, d_cam = np.array([(rho - known) / std]), np.array([rho / std])
    return r_theta, r_person, r_cam, d_cam


def _cost(problem: MapProblem, theta: FloatArray, ankles: FloatArray, person: FloatArray) -> float:
    obs = problem.observations
    r = obs.residuals(problem.cameras(theta), ankles, person[obs.track])[0]
    priors = _prior_terms(problem, theta, person)
    return float(np.sum(r * r) + sum(np.sum(x * x) for x in (priors[0], priors[1], priors[2])))


@dataclass
class _Reduced:
    s: FloatArray  # (p, p) Schur complement on theta
    g: FloatArray  # (p,)
    # Back-substitution pieces.
    x: FloatArray  # (n, 2, p)
    y: FloatArray  # (n, 2, q)
    z: FloatArray  # (n, 2)
    h_inv: FloatArray  # (T, q, q)
    h_t: FloatArray  # (T, q, p)
    g_h: FloatArray  # (T, q)


def _track_sums(values: FloatArray, track: np.ndarray, tracks: int) -> FloatArray:
    """Sum (n, ...) per-observation blocks into (T, ...) per-individual ones: one bincount over the flattened
    blocks (np.add.at is ~4x slower; both add in observation order, so the sums are the same)."""
    width = values[0].size
    index = (track[:, None] * width + np.arange(width)).ravel()
    sums = np.bincount(index, weights=values.ravel(), minlength=tracks * width)
    return sums.reshape((tracks,) + values.shape[1:])


def _reduce(problem: MapProblem, lin: Linearisation, theta: FloatArray, person: FloatArray, damping: float) -> _Reduced:
    """The Schur complement on theta and the pieces of back-substitution.

    Per observation the products of its Jacobian blocks are taken together ([J_a J_h]^T [J_a J_h J_t r] in one
    batched product over the shoulder rows, the ankle rows added as their diagonal weight): a few large
    array operations instead of many small ones.
    """
    obs, layout = problem.observations, problem.layout
    ja, jh, jt, r = lin.j_ankle, lin.j_person, lin.j_theta, lin.r
    p, q, t_count = len(theta), person.shape[1], obs.tracks
    left = np.concatenate((ja, jh), -1)  # (n, 2, 2 + q)
    prod = np.swapaxes(left, 1, 2) @ np.concatenate((left, jt, r[:, 2:, None]), -1)  # (n, 2 + q, 3 + q + p)
    w2 = lin.ankle_weight**2
    u_aa = prod[:, :2, :2] + w2[:, None, None] * np.eye(2)  # (n, 2, 2)
    u_ah = prod[:, :2, 2 : 2 + q]  # (n, 2, q)
    u_hh = prod[:, 2:, 2 : 2 + q]  # (n, q, q)
    w_at = prod[:, :2, 2 + q : 2 + q + p]  # (n, 2, p)
    w_ht = prod[:, 2:, 2 + q : 2 + q + p]  # (n, q, p)
    g_a = prod[:, :2, -1] + lin.ankle_weight[:, None] * r[:, :2]
    g_h = prod[:, 2:, -1]
    flat = jt.reshape(-1, p)
    v_tt = flat.T @ flat
    g_t = flat.T @ r[:, 2:].ravel()

    r_theta, r_person, r_cam, d_cam = _prior_terms(problem, theta, person)
    finite = np.isfinite(layout.prior_std)
    inv_std = np.where(finite, 1.0 / np.where(finite, layout.prior_std, 1.0), 0.0)
    v_tt = v_tt + np.diag(inv_std**2)
    g_t = g_t + inv_std * r_theta
    inv_person = 1.0 / _person_prior_std(problem, q)
    if len(r_cam):
        i = layout.index["log_rho"]
        v_tt[i, i] += float(d_cam[0] ** 2)
        g_t[i] += float(d_cam[0] * r_cam[0])

    # Marquardt damping on every diagonal.
    u_aa = u_aa + damping * np.einsum("nii->ni", u_aa)[:, :, None] * np.eye(2)
    v_tt = v_tt + damping * np.diag(np.diag(v_tt))
    u_inv = _inv2(u_aa)
    solved = u_inv @ np.concatenate((u_ah, w_at, g_a[:, :, None]), -1)  # (n, 2, q + p + 1)
    y, x, z = solved[:, :, :q], solved[:, :, q : q + p], solved[:, :, -1]
    # The individuals' blocks with the ankles eliminated: [hh | ht | gh] - u_ah^T [y | x | z].
    own = np.concatenate((u_hh, w_ht, g_h[:, :, None]), -1) - np.swapaxes(u_ah, 1, 2) @ solved
    summed = _track_sums(own, obs.track, t_count)  # (T, q, q + p + 1)
    h_hh, h_ht, gh_t = summed[:, :, :q], summed[:, :, q : q + p], summed[:, :, -1]
    h_hh = h_hh + np.diag(inv_person**2)
    gh_t = gh_t + inv_person * r_person
    h_hh = h_hh + damping * np.einsum("tii->ti", h_hh)[:, :, None] * np.eye(q)
    h_inv = np.linalg.inv(h_hh)
    w_flat = w_at.reshape(-1, p)
    hw = h_inv @ h_ht  # (T, q, p)
    s = v_tt - w_flat.T @ x.reshape(-1, p) - np.einsum("tkj,tkl->jl", h_ht, hw)
    g = g_t - w_flat.T @ z.ravel() - np.einsum("tkj,tk->j", hw, gh_t)
    return _Reduced(s, g, x, y, z, h_inv, h_ht, gh_t)


def _step(
    problem: MapProblem,
    red: _Reduced,
    ankles: FloatArray,
    person: FloatArray,
    theta: FloatArray,
    frozen: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One Gauss-Newton step from the reduced system; frozen keeps theta and moves only the people."""
    d_theta = np.zeros(len(theta))
    free = problem.layout.estimated
    if not frozen and free.any():
        d_theta[free] = np.linalg.lstsq(red.s[np.ix_(free, free)], -red.g[free], rcond=None)[0]
    d_p = -(red.h_inv @ (red.g_h + red.h_t @ d_theta)[:, :, None])[:, :, 0]
    track = problem.observations.track
    d_a = -(red.z + (red.y @ d_p[track][:, :, None])[:, :, 0] + red.x @ d_theta)
    lower, upper = problem.layout.bounds()
    person = person + d_p
    # Deviations beyond -0.9 would be people of a tenth of the height, leans beyond 0.5 rad falling over.
    person[:, 0] = np.clip(person[:, 0], -0.9, 2.0)
    person[:, 1:] = np.clip(person[:, 1:], -0.5, 0.5)
    return np.clip(theta + d_theta, lower, upper), ankles + d_a, person


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
    person0: FloatArray,
    *,
    optimise: bool = True,
    ankles: FloatArray | None = None,
) -> MapFit:
    """Levenberg-Marquardt from theta0 (latent ankles start at the measured ones unless given, individuals
    at person0, (T, q)); optimise=False holds theta and only evaluates the covariance there."""
    obs = problem.observations
    theta, person = theta0.astype(np.float64), person0.astype(np.float64).copy()
    ankles = obs.bottoms_n.copy() if ankles is None else ankles.copy()
    # optimise=False: people still take their best positions and heights for this camera (theta frozen).
    cost = _cost(problem, theta, ankles, person)
    damping = 1e-4
    iterations = 0
    for iterations in range(1, _MAX_ITERATIONS + 1):  # noqa: B007 - the count is reported
        lin = _linearise(problem, theta, ankles, person)
        converged = True
        for _ in range(12):
            red = _reduce(problem, lin, theta, person, damping)
            candidate = _step(problem, red, ankles, person, theta, frozen=not optimise)
            new_cost = _cost(problem, *candidate)
            if np.isfinite(new_cost) and new_cost <= cost:
                # Converged once the step is far below the parameters' own uncertainty (the Newton
                # decrement in units of the posterior: _CONVERGED_DECREMENT), or when no step lowers the cost
                # (floating-point noise).
                d = candidate[0] - theta
                decrement = float(d @ red.s @ d)
                theta, ankles, person = candidate
                cost = new_cost
                damping = max(damping / 5.0, 1e-9)
                converged = decrement < _CONVERGED_DECREMENT
                break
            damping *= 8.0
        if converged:
            break
    lin = _linearise(problem, theta, ankles, person)
    red = _reduce(problem, lin, theta, person, 0.0)
    covariance = _consider_covariance(problem.layout, red.s)
    per_obs = np.sum(lin.r * lin.r, axis=1)
    data_cost = float(np.sum(per_obs))
    dof = max(2 * len(per_obs) - len(theta), 1)
    r_person = _prior_terms(problem, theta, person)[1]
    # Each observation's cost includes its share of its individual's prior: a person whose height (or lean)
    # had to go far from the population's to fit is as suspect as one whose pixels do not fit.
    track = problem.observations.track
    share = np.sum(r_person**2, axis=1) / np.bincount(track, minlength=len(person))
    return MapFit(
        theta=theta,
        covariance=covariance,
        ankles_n=ankles,
        person=person,
        person_costs=per_obs + share[track],
        data_cost=data_cost,
        variance_factor=(data_cost + float(np.sum(r_person**2))) / dof,
        iterations=iterations,
    )
