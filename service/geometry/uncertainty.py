"""Uncertainty of a calibration in a canonical, self-contained parameterisation.

The refinement's covariance lives on its internal parameters (log focal,
tangent offsets around the starting normal, log rho, nuisances). It is mapped
(service.geometry.posterior.canonical_covariance) to canonical parameters
around the reported solution,

    c = (fx_px, fy_px, t1_rad, t2_rad, rho_m, cx_px, cy_px, k),  N(c) = normalise(N + t1 e1 + t2 e2),

with (e1, e2) = tangent_basis(N) and k the division-model distortion, so anyone
holding a Calibration can propagate it (first order) into any derived quantity
without the solver. The first five are the layout of versions stored before
the principal point and distortion had uncertainties; a 5x5 covariance is read
as those five with the rest exact.
"""

from __future__ import annotations

import numpy as np

from .calibration import Uncertainty
from .model import tangent_basis
from .vec import FloatArray

CANONICAL_PARAMETERS = (
    "fx_px",
    "fy_px",
    "normal_t1_rad",
    "normal_t2_rad",
    "rho_m",
    "cx_px",
    "cy_px",
    "distortion_k",
)


def canonical_camera(
    c: FloatArray, normal: FloatArray, basis: tuple[FloatArray, FloatArray] | None = None
) -> tuple[float, float, FloatArray, float]:
    """(fx_px, fy_px, normal, rho_m) at canonical parameters c around the reported normal.

    `basis` is tangent_basis(normal), for callers that evaluate many c around one normal.
    """
    e1, e2 = basis if basis is not None else tangent_basis(normal)
    n = normal + c[2] * e1 + c[3] * e2
    return float(c[0]), float(c[1]), n / np.linalg.norm(n), float(c[4])


def summarise(cov_c: FloatArray, noise_px: float, noise_per_length: float = 0.0) -> Uncertainty:
    sd = np.sqrt(np.maximum(np.diag(cov_c), 0.0))
    extra = np.zeros(len(CANONICAL_PARAMETERS))
    extra[: len(sd)] = sd
    return Uncertainty(
        fx_px=float(sd[0]),
        fy_px=float(sd[1]),
        normal_deg=float(np.degrees(np.hypot(sd[2], sd[3]))),
        rho_m=float(sd[4]),
        covariance=cov_c,
        noise_px=float(noise_px),
        cx_px=float(extra[5]),
        cy_px=float(extra[6]),
        distortion_k=float(extra[7]),
        noise_per_length=float(noise_per_length),
    )
