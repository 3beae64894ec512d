"""The paper's direct linear solver as printed (its errors corrected), as a reference for the benchmark.

Differences from service.geometry's solver, each one a reason ours is more
accurate: pixel coordinates (only shifted to the principal point, not
scaled), plain unweighted rows for the vanishing point, and people placed from
their own Eq. 1 depths rather than on the fitted ground plane. Running it on
the same simulated scenes gives an apples-to-apples comparison that the
paper's tables, drawn from an unpublished scene distribution, cannot.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from service.geometry import Calibration, CalibrationError
from service.geometry.camera import ImageFrame
from service.geometry.linear import focal_weights, normal_and_rho, scaled_depths, vanishing_point
from service.geometry.vec import homogeneous


def calibrate_paper_literal(
    tops: ArrayLike, bottoms: ArrayLike, image_size: tuple[float, float], height: float, equal_focal: bool
) -> Calibration:
    width, img_h = image_size
    frame = ImageFrame(float(width), float(img_h), width / 2.0, img_h / 2.0, 1.0)  # pixels, no scaling
    t = homogeneous(frame.normalise(np.asarray(tops, dtype=np.float64)))
    b = homogeneous(frame.normalise(np.asarray(bottoms, dtype=np.float64)))
    v = vanishing_point(t, b, irls_iterations=0)[None, :]
    lam_t, lam_b = scaled_depths(t, b, v, height)
    w = focal_weights(b, lam_b, v, equal_focal)
    if not (np.all(np.isfinite(w)) and np.all(w > 0)):
        raise CalibrationError("non-positive 1/f^2")
    focal = 1.0 / np.sqrt(w)
    normal, rho = normal_and_rho(t, b, v, lam_t, lam_b, focal, height)
    mu = float(np.linalg.norm(v[0] * np.append(1.0 / focal, 1.0))) * float(np.sign(np.median(lam_b)) or 1.0)
    k_inv = np.append(1.0 / focal, 1.0)
    x_b = b * k_inv * (lam_b / mu)[:, None]
    x_t = t * k_inv * (lam_t / mu)[:, None]
    n = len(t)
    return Calibration(
        fx=float(focal[0]),
        fy=float(focal[1]),
        cx=frame.cx_px,
        cy=frame.cy_px,
        normal=normal,
        rho=float(rho),
        image_size=(float(width), float(img_h)),
        height_m=height,
        points_bottom=x_b,
        points_top=x_t,
        heights=np.full(n, height),
        inliers=np.ones(n, bool),
    )
