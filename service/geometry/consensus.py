"""Which people agree on one camera: the generic RANSAC loop applied to people (paper Sect. 3.4).

A hypothesis is solved from a minimal sample of people (service.geometry.minimal),
then scored on every person at once. Inlier test, per person, for a hypothesis
(K, N, rho):

* direction: the Sampson distance of the segment from pointing at the vertical
  vanishing point K N is below ``inlier_px`` pixels. It is independent of the
  person's height, so it measures only keypoint noise and non-vertical bodies
  (bending, bad detections);
* height: the person placed on the hypothesised ground has an implied height
  within ``height_tolerance`` (relative) of the prior. This catches people whose
  direction is fine but whose scale is not: sitting people, people on stairs.

Both residuals come from the definitions every other stage uses
(linear.sampson_distances, reconstruct.heights_above_ground), broadcast over the
hypotheses. They are combined into one MSAC cost c = (d/inlier_px)^2 +
((h/h0 - 1)/height_tolerance)^2, truncated at 1; an inlier has c < 1.

Once a winner exists, the keypoint noise is estimated from everyone's
direction residuals (median absolute deviation) and both tests are widened to
3 sigma of it, the height test per person by the relative error that noise
causes on that person's segment length; the winner is then refitted by the
batch solver on its inliers (twice, re-selecting inliers in between).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .camera import rays
from .errors import CalibrationError
from .linear import LinearSolution, sampson_distances, solve_linear
from .minimal import minimal_size, solve_minimal
from .ransac import Hypotheses, RansacOptions, ransac
from .reconstruct import heights_above_ground, intersect_plane
from .vec import FloatArray, homogeneous


@dataclass(frozen=True)
class ConsensusSettings:
    inlier_px: float
    height_tolerance: float = 0.2
    ransac: RansacOptions = field(default_factory=RansacOptions)
    # Keypoint noise (px) once estimated: widens both tests so that noisy
    # detections (and the short segments of distant people) are not thrown out.
    noise_px: float = 0.0


@dataclass(frozen=True)
class Consensus:
    solution: LinearSolution
    inliers: FloatArray
    iterations: int


def vanishing_points(focal_n: FloatArray, normal: FloatArray) -> FloatArray:
    """v = K N in normalised units, for (..., 2) focal lengths and (..., 3) normals."""
    return np.stack((normal[..., 0] * focal_n[..., 0], normal[..., 1] * focal_n[..., 1], normal[..., 2]), -1)


def score_hypotheses(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    focal: FloatArray,
    normal: FloatArray,
    rho: FloatArray,
    height_m: float,
    scale_px: float,
    settings: ConsensusSettings,
) -> FloatArray:
    """(M, N) truncated MSAC costs in [0, 1] of M hypotheses on N people; < 1 means inlier."""
    tops_h, bottoms_h = homogeneous(tops_n)[None], homogeneous(bottoms_n)[None]
    normal_m = normal[:, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        d_px = sampson_distances(tops_h, bottoms_h, vanishing_points(focal, normal)[:, None, :]) * scale_px
        # A person whose ankle ray misses the ground gets NaN here, hence cost 1 below.
        x_b = intersect_plane(rays(bottoms_n[None], focal[:, None, :]), normal_m, rho[:, None])
        h = heights_above_ground(x_b, rays(tops_n[None], focal[:, None, :]), normal_m)
        inlier_px = max(settings.inlier_px, 3.0 * settings.noise_px)
        length_px = np.hypot(*(tops_n - bottoms_n).T) * scale_px
        tolerance2 = settings.height_tolerance**2 + (3.0 * np.sqrt(2.0) * settings.noise_px / length_px) ** 2
        cost = (d_px / inlier_px) ** 2 + (h / height_m - 1.0) ** 2 / tolerance2
    return np.minimum(np.where(np.isfinite(cost), cost, 1.0), 1.0)


def find_consensus(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    height_m: float,
    equal_focal: bool,
    focal_n: tuple[float, float] | None,
    scale_px: float,
    settings: ConsensusSettings,
    rng: np.random.Generator,
) -> Consensus:
    """RANSAC over minimal samples of people, then the noise-widened refits described in the module docstring."""
    m = minimal_size(equal_focal, focal_n is not None)
    tops_h, bottoms_h = homogeneous(tops_n), homogeneous(bottoms_n)

    def propose(samples: np.ndarray) -> Hypotheses:
        focal, normal, rho, _ = solve_minimal(tops_h[samples], bottoms_h[samples], height_m, equal_focal, focal_n)
        ok = np.all(np.isfinite(focal), 1) & np.all(np.isfinite(normal), 1) & (rho > 0)
        return focal[ok], normal[ok], rho[ok]

    def score(hypotheses: Hypotheses) -> FloatArray:
        return score_hypotheses(tops_n, bottoms_n, *hypotheses, height_m, scale_px, settings)

    found = ransac(len(tops_n), m, propose, score, settings.ransac, rng)
    focal, normal, rho = found.model
    solution = LinearSolution((float(focal[0]), float(focal[1])), normal, float(rho))
    inliers = found.inliers
    v = vanishing_points(np.asarray(solution.focal_n), solution.normal)
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
    return Consensus(solution, inliers, found.iterations)
