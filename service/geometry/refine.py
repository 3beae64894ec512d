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
then three entries per person: ankle u, ankle v (normalised), height (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

from .frame import FloatArray
from .linear import LinearSolution

RESIDUALS_PER_PERSON = 5
PARAMS_PER_PERSON = 3


def tangent_basis(normal: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors orthogonal to normal and to each other."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = np.cross(normal, helper)
    t1 /= np.linalg.norm(t1)
    return t1, np.cross(normal, t1)


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

    def block_jacobian(self, theta: FloatArray, persons: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Forward-difference Jacobian blocks: camera (N, 5, nc) and each person's own (N, 5, 3)."""
        base = self.person_residuals(theta, persons)
        jc = np.empty(base.shape + (len(theta),))
        for k in range(len(theta)):
            step = 1e-7 * max(1.0, abs(theta[k]))
            t = theta.copy()
            t[k] += step
            jc[:, :, k] = (self.person_residuals(t, persons) - base) / step
        jp = np.empty(base.shape + (PARAMS_PER_PERSON,))
        for k in range(PARAMS_PER_PERSON):
            step = 1e-7 * np.maximum(1.0, np.abs(persons[:, k]))
            p = persons.copy()
            p[:, k] += step
            jp[:, :, k] = (self.person_residuals(theta, p) - base) / step[:, None]
        return jc, jp

    def split(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        nc = self.camera.size
        return x[:nc], x[nc:].reshape(-1, PARAMS_PER_PERSON)

    def fun(self, x: FloatArray) -> FloatArray:
        return self.person_residuals(*self.split(x)).ravel()

    def jac(self, x: FloatArray) -> sparse.csr_matrix:
        jc, jp = self.block_jacobian(*self.split(x))
        n, r, nc = jc.shape
        rows = np.arange(n * r)
        cam = sparse.csr_matrix((jc.reshape(n * r, nc).ravel(), (np.repeat(rows, nc), np.tile(np.arange(nc), n * r))),
                                shape=(n * r, nc + PARAMS_PER_PERSON * n))
        person_cols = nc + PARAMS_PER_PERSON * np.arange(n)[:, None, None] + np.arange(PARAMS_PER_PERSON)[None, None, :]
        person_cols = np.broadcast_to(person_cols, jp.shape)
        person_rows = np.broadcast_to(rows.reshape(n, r)[:, :, None], jp.shape)
        per = sparse.csr_matrix((jp.ravel(), (person_rows.ravel(), person_cols.ravel())), shape=cam.shape)
        return (cam + per).tocsr()


def camera_covariance(jc: FloatArray, jp: FloatArray, residuals: FloatArray) -> FloatArray:
    """Covariance of the camera block: inverse Schur complement of J'J, scaled by the residual variance.

    The per-person blocks are eliminated exactly (3x3 each), so this is the
    full Gauss-Newton marginal covariance of theta at O(N) cost.
    """
    u = np.einsum("nri,nrj->ij", jc, jc)
    w = np.einsum("nri,nrj->nij", jc, jp)
    v = np.einsum("nri,nrj->nij", jp, jp)
    v_inv_wt = np.linalg.solve(v, np.swapaxes(w, 1, 2))
    schur = u - np.einsum("nij,njk->ik", w, v_inv_wt)
    dof = max(residuals.size - jc.shape[2] - jp.shape[0] * jp.shape[2], 1)
    variance_factor = float(np.sum(residuals**2)) / dof
    return np.linalg.pinv(schur) * variance_factor


@dataclass(frozen=True)
class Refinement:
    solution: LinearSolution
    ankles_n: FloatArray  # refined (noise-free) ankle centres, normalised
    heights_m: FloatArray
    theta: FloatArray
    covariance: FloatArray
    camera: CameraModel
    rms_residual: float


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
    max_evaluations: int = 50,
) -> Refinement:
    """The ML polish of start (optimise=True), or only its covariance (optimise=False)."""
    camera = CameraModel(start.normal, equal_focal, focal_n)
    problem = ReprojectionProblem(camera, tops_n, bottoms_n, noise_n, height_m, height_std_m)
    heights0 = np.clip(np.nan_to_num(start_heights_m, nan=height_m), 0.5 * height_m, 1.5 * height_m)
    x = np.concatenate((camera.pack(start), np.column_stack((bottoms_n, heights0)).ravel()))
    if optimise:
        x = least_squares(
            problem.fun, x, jac=problem.jac, method="trf", x_scale="jac", max_nfev=max_evaluations, tr_solver="lsmr"
        ).x
    theta, persons = problem.split(x)
    focal, normal, rho = camera.unpack(theta)
    jc, jp = problem.block_jacobian(theta, persons)
    residuals = problem.person_residuals(theta, persons)
    return Refinement(
        solution=LinearSolution((float(focal[0]), float(focal[1])), normal, rho),
        ankles_n=persons[:, :2],
        heights_m=persons[:, 2],
        theta=theta,
        covariance=camera_covariance(jc, jp, residuals),
        camera=camera,
        rms_residual=float(np.sqrt(np.mean(residuals[:, :4] ** 2))) * noise_n,
    )
