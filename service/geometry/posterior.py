"""From a consensus to the posterior: the noise model, the MAP fit with its nuisances, and misfit rejection.

Noise. Keypoint noise is not one number: pose models err in proportion to a person's size (their
heatmaps live on a crop scaled to the person), and walking people lean, which moves the shoulders in
proportion to the segment's length l. Each observation therefore gets sigma_o^2 = sigma^2 + (lambda l_o)^2
on both centres. Both are estimated from the height-free direction residuals: the Sampson distance d_o of a
segment from the vertical vanishing point has variance sigma^2 + lambda^2 l_o^2 under that model, so the
medians of d^2 in groups of similar l, divided by 0.455 (the median of chi^2_1), are fitted by non-negative
least squares in (sigma^2, lambda^2). A floor keeps the likelihood well conditioned on perfect input.

Lean is partly an individual's: a walking posture persists from frame to frame, so when observations are
linked into individuals the lean they keep is a per-individual latent (service.geometry.model) with its
spread estimated by `estimate_noise_and_lean`, and only the frame-to-frame part stays in the noise.

Calibrated sigma. The covariance is the posterior's, S^-1 from the reduced normal equations, with the data
whitened by the estimated noise. When the data misfit that noise (mean square per degree of freedom above
1: unmodelled effects), the noise is scaled up by that factor and the covariance recomputed, so the data's
weight drops while the priors keep theirs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import nnls

from .consensus import vanishing_points
from .linear import LinearSolution, sampson_distances
from .model import Layout, Observations, Priors, tangent_basis
from .refine import MapFit, MapProblem, fit_map
from .vec import FloatArray, homogeneous

# Floor of the keypoint noise estimate, as a fraction of the image diagonal
# (0.04 px at 1080p). No pose model is better than this; it keeps the
# likelihood well conditioned on perfect synthetic input. Relative, so that
# scaling an image and its points changes nothing but f.
MIN_NOISE_FRACTION = 2e-5
# The size-proportional noise is estimated only from this many people (fewer: sigma alone).
_MIN_PEOPLE_FOR_LEAN = 40
_LEAN_GROUPS = 4
_MAX_LEAN = 0.15
_MIN_TRACKS_FOR_LEAN = 5

# A person whose whitened residual cost exceeds this (chi^2 with 2 degrees of
# freedom: 4 pixel residuals and q prior residuals minus 2 ankle and q own
# parameters, p = 0.999) is not explained by the camera and is dropped before
# the final fit.
_CHI2_2DOF_999 = 13.8
_CHI2_2DOF_MEDIAN = 1.386


@dataclass(frozen=True)
class NoiseModel:
    """sigma_o = sqrt(sigma^2 + (lean l_o)^2), normalised units and a ratio."""

    sigma_n: float
    lean: float

    def per_observation(self, length_n: FloatArray) -> FloatArray:
        return np.sqrt(self.sigma_n**2 + (self.lean * length_n) ** 2)


def direction_residuals_n(tops_n: FloatArray, bottoms_n: FloatArray, solution: LinearSolution) -> FloatArray:
    v = vanishing_points(np.asarray(solution.focal_n), solution.normal)
    return sampson_distances(homogeneous(tops_n), homogeneous(bottoms_n), v)


def estimate_noise(d_n: FloatArray, length_n: FloatArray, floor_n: float) -> NoiseModel:
    """(sigma, lambda) from direction residuals and segment lengths (see the module docstring)."""
    n = len(d_n)
    dof_scale = n / max(n - 2, 1)  # the vanishing point's two degrees of freedom
    d2 = d_n * d_n * dof_scale
    if n < _MIN_PEOPLE_FOR_LEAN:
        return NoiseModel(max(float(np.sqrt(np.median(d2) / 0.455)), floor_n), 0.0)
    order = np.argsort(length_n)
    groups = np.array_split(order, _LEAN_GROUPS)
    variance = np.array([np.median(d2[g]) / 0.455 for g in groups])
    l2 = np.array([np.mean(length_n[g] ** 2) for g in groups])
    (s2, lam2), _ = nnls(np.column_stack((np.ones(len(groups)), l2)), variance)
    lean = min(float(np.sqrt(lam2)), _MAX_LEAN)
    return NoiseModel(max(float(np.sqrt(s2)), floor_n), lean)


def estimate_noise_and_lean(
    d_n: FloatArray, length_n: FloatArray, tracks: np.ndarray, floor_n: float
) -> tuple[NoiseModel, float]:
    """The noise within an individual's observations, and the spread of individuals' lean (radians).

    A one-way analysis of variance of the direction residuals over individuals seen more than once: the
    residuals' deviations from their individual's mean angle (d_o - l_o mean_t(d / l), scaled by m / (m - 1)
    for the mean's own degree of freedom) give the frame-to-frame noise; the individuals' mean angles, less
    what that noise explains of them, give the lean they keep from frame to frame. Without individuals seen
    twice (or with fewer than _MIN_TRACKS_FOR_LEAN of them) the lean cannot be told from noise: it is 0 and
    the size-proportional noise carries it.
    """
    labels, track = np.unique(tracks, return_inverse=True)
    counts = np.bincount(track, minlength=len(labels))
    repeated = counts[track] >= 2
    if (counts >= 2).sum() < _MIN_TRACKS_FOR_LEAN or repeated.sum() < _MIN_PEOPLE_FOR_LEAN:
        return estimate_noise(d_n, length_n, floor_n), 0.0
    angle = d_n / length_n
    mean_angle = np.bincount(track, angle, len(labels)) / np.maximum(counts, 1)
    m = counts[track][repeated]
    within = (d_n - length_n * mean_angle[track])[repeated] * np.sqrt(m / (m - 1.0))
    noise = estimate_noise(within, length_n[repeated], floor_n)
    multi = counts >= 2
    explained = (
        np.bincount(track[repeated], (noise.sigma_n / length_n[repeated]) ** 2 + noise.lean**2, len(labels))[multi]
        / counts[multi] ** 2
    )
    between2 = float(np.median(mean_angle[multi] ** 2) / 0.455 - np.median(explained))
    return noise, min(float(np.sqrt(max(between2, 0.0))), _MAX_LEAN)


def observations(tops_n: FloatArray, bottoms_n: FloatArray, tracks: np.ndarray, noise: NoiseModel) -> Observations:
    labels, track = np.unique(tracks, return_inverse=True)
    std = noise.per_observation(np.hypot(*(tops_n - bottoms_n).T))
    return Observations(tops_n, bottoms_n, std, std, track.ravel(), len(labels))


def initial_theta(layout: Layout, solution: LinearSolution, k: float) -> FloatArray:
    values = {
        "log_f": np.log(solution.focal_n[0]),
        "log_fy": np.log(solution.focal_n[1]),
        "aspect": 0.0,
        "log_rho": np.log(solution.rho_m),
        "k": k,
    }
    return np.array([values.get(name, 0.0) for name in layout.names], dtype=np.float64)


def start_people(heights_m: FloatArray, obs: Observations, prior_m: float, q: int) -> FloatArray:
    """(T, q) starting individuals: height relative to the prior (the mean over the observations, clipped),
    upright."""
    h = np.clip(np.nan_to_num(heights_m / prior_m - 1.0, nan=0.0), -0.5, 0.5)
    start = np.zeros((obs.tracks, q))
    start[:, 0] = np.bincount(obs.track, h, obs.tracks) / np.maximum(np.bincount(obs.track, minlength=obs.tracks), 1)
    return start


@dataclass(frozen=True)
class Posterior:
    problem: MapProblem
    fit: MapFit
    noise: NoiseModel
    kept: np.ndarray  # (n,) bool over the observations given: those the final fit used


def fit_posterior(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    tracks: np.ndarray,
    layout: Layout,
    priors: Priors,
    solution: LinearSolution,
    k: float,
    start_heights_m: FloatArray,
    mu0: float,
    noise: NoiseModel,
    *,
    optimise: bool,
    reject: bool,
    minimum_people: int,
) -> Posterior:
    """The MAP fit, a likelihood-based second inlier test with one refit, and the variance-factor check."""
    obs = observations(tops_n, bottoms_n, tracks, noise)
    problem = MapProblem(layout, priors, obs, solution.normal, mu0)
    theta0 = initial_theta(layout, solution, k)
    q = 2 if priors.lean_rad > 0 else 1
    fit = fit_map(problem, theta0, start_people(start_heights_m, obs, mu0, q), optimise=optimise)
    kept = np.ones(len(tops_n), dtype=bool)
    if optimise and reject:
        # RANSAC's tests are coarse (fixed tolerances); the fitted model knows each person's expected
        # residual, so mild outliers that slipped through (people on a step, leaning) stand out here. The cut
        # scales with the median cost so a misjudged noise level cannot make it reject everyone.
        cost = fit.person_costs
        cut = _CHI2_2DOF_999 * max(float(np.median(cost)) / _CHI2_2DOF_MEDIAN, 1.0)
        keep = cost <= cut
        if not keep.all() and keep.sum() >= max(minimum_people, 0.5 * len(keep)):
            kept = keep
            heights_o = mu0 * (1.0 + fit.person[obs.track[keep], 0])
            obs = observations(tops_n[keep], bottoms_n[keep], tracks[keep], noise)
            problem = replace(problem, observations=obs)
            fit = fit_map(problem, fit.theta, start_people(heights_o, obs, mu0, q))
    if fit.variance_factor > 1.0:
        scale = float(np.sqrt(fit.variance_factor))
        noise = NoiseModel(noise.sigma_n * scale, noise.lean * scale)
        obs = replace(obs, ankle_std_n=obs.ankle_std_n * scale, top_std_n=obs.top_std_n * scale)
        problem = replace(problem, observations=obs)
        again = fit_map(problem, fit.theta, fit.person, optimise=False, ankles=fit.ankles_n)
        fit = replace(fit, covariance=again.covariance)
    return Posterior(problem, fit, noise, kept)


def with_groups(posterior: Posterior, groups: np.ndarray) -> Posterior:
    """The posterior with theta's covariance evaluated with one height (and lean) per group of `groups` (one label
    per fitted observation) instead of one per individual: the same camera, the sigma of a sample in which each group
    may be one person (tracks.possible_repeats). Unchanged when the groups are the individuals."""
    obs, fit = posterior.problem.observations, posterior.fit
    labels = np.unique(groups, return_inverse=True)[1].ravel()
    if len(np.unique(labels)) == obs.tracks and len(np.unique(obs.track * (labels.max() + 1) + labels)) == obs.tracks:
        return posterior
    grouped = replace(obs, track=labels, tracks=int(labels.max()) + 1)
    problem = replace(posterior.problem, observations=grouped)
    mu = float(problem.cameras(fit.theta).mu[0, 0])
    heights_m = mu * (1.0 + fit.person[obs.track, 0])
    start = start_people(heights_m, grouped, mu, fit.person.shape[1])
    # theta held: each group takes its best height for this camera, and the covariance is evaluated there.
    again = fit_map(problem, fit.theta, start, optimise=False, ankles=fit.ankles_n)
    return replace(posterior, fit=replace(fit, covariance=again.covariance))


def canonical_covariance(problem: MapProblem, theta: FloatArray, cov_theta: FloatArray, scale_px: float) -> FloatArray:
    """Covariance of the canonical parameters (uncertainty.CANONICAL_PARAMETERS) from theta's (first order)."""
    cams = problem.cameras(theta)
    normal_hat = cams.normal[0, 0]
    e1, e2 = tangent_basis(normal_hat)

    def canonical(t: FloatArray) -> FloatArray:
        c = problem.cameras(t)
        n = c.normal[0, 0]
        return np.array(
            [
                c.fx[0, 0] * scale_px,
                c.fy[0, 0] * scale_px,
                (n @ e1) / (n @ normal_hat),
                (n @ e2) / (n @ normal_hat),
                c.rho[0, 0],
                c.c[0, 0, 0] * scale_px,
                c.c[0, 0, 1] * scale_px,
                c.k[0, 0],
            ]
        )

    base = canonical(theta)
    jac = np.empty((len(base), len(theta)))
    for i in range(len(theta)):
        step = 1e-7 * max(1.0, abs(theta[i]))
        t = theta.copy()
        t[i] += step
        jac[:, i] = (canonical(t) - base) / step
    return jac @ cov_theta @ jac.T
