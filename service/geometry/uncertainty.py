"""Uncertainty of a calibration and of the distances measured with it.

The refinement's covariance lives on its internal parameters (log focal,
tangent offsets around the starting normal, log rho). It is mapped here to a
canonical, self-contained parameterisation around the reported solution,

    c = (fx_px, fy_px, t1_rad, t2_rad, rho_m),  N(c) = normalise(N + t1 e1 + t2 e2),

with (e1, e2) = tangent_basis(N), so anyone holding a Calibration can
propagate it (first order) into any derived quantity without the solver.
"""

from __future__ import annotations

import numpy as np

from .calibration import Uncertainty
from .refine import CameraModel, tangent_basis
from .vec import FloatArray

CANONICAL_PARAMETERS = ("fx_px", "fy_px", "normal_t1_rad", "normal_t2_rad", "rho_m")


def canonical_camera(
    c: FloatArray, normal: FloatArray, basis: tuple[FloatArray, FloatArray] | None = None
) -> tuple[float, float, FloatArray, float]:
    """(fx_px, fy_px, normal, rho_m) at canonical parameters c around the reported normal.

    `basis` is tangent_basis(normal), for callers that evaluate many c around one normal.
    """
    e1, e2 = basis if basis is not None else tangent_basis(normal)
    n = normal + c[2] * e1 + c[3] * e2
    return float(c[0]), float(c[1]), n / np.linalg.norm(n), float(c[4])


def canonical_covariance(camera: CameraModel, theta: FloatArray, cov_theta: FloatArray, scale_px: float) -> FloatArray:
    """5x5 covariance of c from the covariance of the internal parameters theta (first order)."""
    _, normal_hat, _ = camera.unpack(theta)
    e1, e2 = tangent_basis(normal_hat)

    def to_canonical(t: FloatArray) -> FloatArray:
        focal, n, rho = camera.unpack(t)
        # Inverse of canonical_camera's map: tangent offsets of n around normal_hat.
        return np.array(
            [focal[0] * scale_px, focal[1] * scale_px, (n @ e1) / (n @ normal_hat), (n @ e2) / (n @ normal_hat), rho]
        )

    base = to_canonical(theta)
    jac = np.empty((5, len(theta)))
    for k in range(len(theta)):
        step = 1e-7 * max(1.0, abs(theta[k]))
        t = theta.copy()
        t[k] += step
        jac[:, k] = (to_canonical(t) - base) / step
    return jac @ cov_theta @ jac.T


def summarise(cov_c: FloatArray, noise_px: float) -> Uncertainty:
    sd = np.sqrt(np.maximum(np.diag(cov_c), 0.0))
    return Uncertainty(
        fx_px=float(sd[0]),
        fy_px=float(sd[1]),
        normal_deg=float(np.degrees(np.hypot(sd[2], sd[3]))),
        rho_m=float(sd[4]),
        covariance=cov_c,
        noise_px=float(noise_px),
    )
