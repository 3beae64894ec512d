"""Maximum-likelihood polish of the linear solution (scipy.optimize.least_squares).

The linear solver minimises algebraic errors and treats every person as
exactly h tall. Here each person instead gets a latent ankle position (on the
ground, parameterised by its undistorted ankle pixel) and a latent height
under a Gaussian prior, and the camera (focal length(s), normal, rho) is
chosen to minimise the reprojection error of both keypoints in units of the
keypoint noise plus the height prior in units of its standard deviation. That
is the likelihood of the generative model the simulator draws from, so its
minimum is the statistically efficient estimate, and its Jacobian at the
minimum gives the covariance used for uncertainties.

Internal parameter vector: camera block theta = [log fx_n, (log fy_n), alpha,
beta, log rho] (focal entries absent when the focal length is known), where
the normal is normalise(N0 + alpha t1 + beta t2) around the initial normal N0;
then, eliminated per camera, three entries per person: ankle u, ankle v
(normalised), height (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .linear import LinearSolution
from .vec import FloatArray, cross

PARAMS_PER_PERSON = 3


def tangent_basis(normal: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors orthogonal to normal and to each other."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = cross(normal, helper)
    t1 /= np.linalg.norm(t1)
    return t1, cross(normal, t1)


@dataclass
class CameraModel:
    """Maps the camera block theta to (focal_n, normal, rho) and back."""

    normal0: FloatArray
    equal_focal: bool
    focal_n: tuple[float, float] | None  # known focal length: not estimated

    def __post_init__(self) -> None:
        self.t1, self.t2 = tangent_basis(self.normal0)

    @property
    def size(self) -> int:
        return (0 if self.focal_n is not None else 1 if self.equal_focal else 2) + 3

    def pack(self, solution: LinearSolution) -> FloatArray:
        n = solution.normal
        alpha, beta = (n @ self.t1) / (n @ self.normal0), (n @ self.t2) / (n @ self.normal0)
        focal: list[float] = []
        if self.focal_n is None:
            focal = [np.log(solution.focal_n[0])] if self.equal_focal else list(np.log(solution.focal_n))
        return np.array([*focal, alpha, beta, np.log(solution.rho_m)])

    def unpack(self, theta: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        nf = self.size - 3
        if self.focal_n is not None:
            focal = np.asarray(self.focal_n, dtype=np.float64)
        elif self.equal_focal:
            focal = np.exp(np.array([theta[0], theta[0]]))
        else:
            focal = np.exp(theta[:2])
        normal = self.normal0 + theta[nf] * self.t1 + theta[nf + 1] * self.t2
        return focal, normal / np.linalg.norm(normal), float(np.exp(theta[nf + 2]))


@dataclass
class ReprojectionProblem:
    """Whitened residuals of all people, as (N, 5) blocks: ankle (2), shoulder (2), height prior (1)."""

    camera: CameraModel
    tops_n: FloatArray
    bottoms_n: FloatArray
    noise_n: float  # keypoint noise std in normalised units
    height_m: float
    height_std_m: float

    def person_residuals(self, theta: FloatArray, persons: FloatArray) -> FloatArray:
        focal, normal, rho = self.camera.unpack(theta)
        ankle = persons[:, :2]
        heights = persons[:, 2]
        ray = np.concatenate((ankle / focal, np.ones((len(ankle), 1))), 1)
        denom = ray @ normal
        # A ray that does not reach the ground is pushed back by a large but finite residual.
        denom = np.minimum(denom, -1e-9)
        x_top = ray * (-rho / denom)[:, None] + heights[:, None] * normal
        z = np.maximum(x_top[:, 2], 1e-9)
        top = focal * x_top[:, :2] / z[:, None]
        return np.concatenate(
            (
                (ankle - self.bottoms_n) / self.noise_n,
                (top - self.tops_n) / self.noise_n,
                ((heights - self.height_m) / self.height_std_m)[:, None],
            ),
            1,
        )

    def camera_bounds(self) -> tuple[FloatArray, FloatArray]:
        """Box that keeps the search physical (and exp() finite) on hopeless inputs."""
        nf = self.camera.size - 3
        lower = np.array([np.log(0.02)] * nf + [-2.0, -2.0, np.log(1e-3)])
        upper = np.array([np.log(200.0)] * nf + [2.0, 2.0, np.log(1e5)])
        return lower, upper

    def solve_persons(self, theta: FloatArray, persons: FloatArray, iterations: int = 8) -> FloatArray:
        """Each person's best (ankle, height) for a fixed camera: batched Gauss-Newton on 3x3 systems."""
        lower = np.array([-10.0, -10.0, 0.1 * self.height_m])
        upper = np.array([10.0, 10.0, 5.0 * self.height_m])
        for _ in range(iterations):
            r = self.person_residuals(theta, persons)
            jp = self._person_jacobian(theta, persons, r)
            jt = np.swapaxes(jp, 1, 2)
            step = -(inverse_3x3(jt @ jp) @ (jt @ r[..., None]))[..., 0]
            persons = np.clip(persons + step, lower, upper)
            # Converged far below any keypoint noise: 1e-9 normalised is ~1e-6 px; heights to 1e-9 m.
            if np.max(np.abs(step)) < 1e-9:
                break
        return persons

    def _person_jacobian(self, theta: FloatArray, persons: FloatArray, base: FloatArray) -> FloatArray:
        jp = np.empty(base.shape + (PARAMS_PER_PERSON,))
        for k in range(PARAMS_PER_PERSON):
            step = 1e-7 * np.maximum(1.0, np.abs(persons[:, k]))
            p = persons.copy()
            p[:, k] += step
            jp[:, :, k] = (self.person_residuals(theta, p) - base) / step[:, None]
        return jp

    def camera_jacobian(self, theta: FloatArray, persons: FloatArray, base: FloatArray) -> FloatArray:
        jc = np.empty(base.shape + (len(theta),))
        for k in range(len(theta)):
            step = 1e-7 * max(1.0, abs(theta[k]))
            t = theta.copy()
            t[k] += step
            jc[:, :, k] = (self.person_residuals(t, persons) - base) / step
        return jc

    def block_jacobian(self, theta: FloatArray, persons: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Forward-difference Jacobian blocks: camera (N, 5, nc) and each person's own (N, 5, 3)."""
        base = self.person_residuals(theta, persons)
        return self.camera_jacobian(theta, persons, base), self._person_jacobian(theta, persons, base)


def reduced_jacobian(jc: FloatArray, jp: FloatArray) -> FloatArray:
    """Jacobian of the residuals with every person's parameters re-optimised (variable projection).

    Kaufman's form: project each person's camera block onto the orthogonal
    complement of that person's own Jacobian columns.
    """
    jt = np.swapaxes(jp, 1, 2)
    return jc - jp @ (inverse_3x3(jt @ jp) @ (jt @ jc))


def inverse_3x3(m: FloatArray) -> FloatArray:
    """Batched inverse of symmetric positive (semi)definite 3x3 matrices by the adjugate.

    Much faster than numpy's batched LAPACK calls for millions of tiny systems;
    a (near-)singular block, a person who carries no information, gets a zero
    inverse instead of infinities.
    """
    a, b, c = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    d, e, f = m[:, 1, 1], m[:, 1, 2], m[:, 2, 2]
    adj = np.empty_like(m)
    adj[:, 0, 0] = d * f - e * e
    adj[:, 0, 1] = adj[:, 1, 0] = c * e - b * f
    adj[:, 0, 2] = adj[:, 2, 0] = b * e - c * d
    adj[:, 1, 1] = a * f - c * c
    adj[:, 1, 2] = adj[:, 2, 1] = b * c - a * e
    adj[:, 2, 2] = a * d - b * b
    det = a * adj[:, 0, 0] + b * adj[:, 0, 1] + c * adj[:, 0, 2]
    scale = np.maximum(a * d * f, 1e-300)
    inv_det = np.where(np.abs(det) > 1e-14 * scale, 1.0 / np.where(det == 0, 1.0, det), 0.0)
    return adj * inv_det[:, None, None]


def camera_covariance(jc: FloatArray, jp: FloatArray, residuals: FloatArray) -> FloatArray:
    """Marginal covariance of the camera block, scaled by the residual variance.

    With the people's parameters projected out, J_red' J_red is exactly the
    Schur complement of J'J, so its inverse is the Gauss-Newton marginal
    covariance of theta at O(N) cost.
    """
    j_red = reduced_jacobian(jc, jp).reshape(-1, jc.shape[2])
    dof = max(residuals.size - jc.shape[2] - jp.shape[0] * jp.shape[2], 1)
    variance_factor = float(np.sum(residuals**2)) / dof
    return np.linalg.pinv(j_red.T @ j_red) * variance_factor


@dataclass(frozen=True)
class Refinement:
    solution: LinearSolution
    ankles_n: FloatArray  # refined (noise-free) ankle centres, normalised
    heights_m: FloatArray
    theta: FloatArray
    covariance: FloatArray
    camera: CameraModel
    rms_residual: float
    noise_n: float
    person_costs: FloatArray  # sum of each person's squared whitened residuals


def fit_camera(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    start: LinearSolution,
    start_heights_m: FloatArray,
    height_m: float,
    height_std_m: float,
    noise_n: float,
    equal_focal: bool,
    focal_n: tuple[float, float] | None,
    optimise: bool = True,
    max_evaluations: int = 100,
) -> Refinement:
    """The ML polish of start (optimise=True), or only its covariance (optimise=False).

    least_squares searches over the few camera parameters only; for each
    camera it is offered, every person's ankle and height are optimised in
    closed batches (variable projection). That keeps the search small and dense,
    O(N) per step, and it converges to the joint optimum.
    """
    camera = CameraModel(start.normal, equal_focal, focal_n)
    problem = ReprojectionProblem(camera, tops_n, bottoms_n, noise_n, height_m, height_std_m)
    heights0 = np.clip(np.nan_to_num(start_heights_m, nan=height_m), 0.5 * height_m, 1.5 * height_m)
    persons = problem.solve_persons(camera.pack(start), np.column_stack((bottoms_n, heights0)))
    theta = camera.pack(start)
    if optimise:
        cache: dict[bytes, FloatArray] = {}

        def residuals(t: FloatArray) -> FloatArray:
            nonlocal persons
            persons = problem.solve_persons(t, persons)
            cache[t.tobytes()] = persons
            return problem.person_residuals(t, persons).ravel()

        def jacobian(t: FloatArray) -> FloatArray:
            p = cache.get(t.tobytes())
            p = problem.solve_persons(t, persons) if p is None else p
            jc, jp = problem.block_jacobian(t, p)
            return reduced_jacobian(jc, jp).reshape(-1, len(t))

        lower, upper = problem.camera_bounds()
        theta = np.clip(theta, lower + 1e-9, upper - 1e-9)
        theta = least_squares(
            residuals,
            theta,
            jac=jacobian,
            bounds=(lower, upper),
            method="trf",
            x_scale="jac",
            ftol=1e-12,
            xtol=1e-12,
            gtol=1e-12,
            max_nfev=max_evaluations,
        ).x
        persons = problem.solve_persons(theta, cache.get(theta.tobytes(), persons))
    focal, normal, rho = camera.unpack(theta)
    jc, jp = problem.block_jacobian(theta, persons)
    residual_blocks = problem.person_residuals(theta, persons)
    return Refinement(
        solution=LinearSolution((float(focal[0]), float(focal[1])), normal, rho),
        ankles_n=persons[:, :2],
        heights_m=persons[:, 2],
        theta=theta,
        covariance=camera_covariance(jc, jp, residual_blocks),
        camera=camera,
        rms_residual=float(np.sqrt(np.mean(residual_blocks[:, :4] ** 2))) * noise_n,
        noise_n=noise_n,
        person_costs=np.sum(residual_blocks**2, axis=1),
    )
