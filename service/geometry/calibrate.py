"""calibrate(): the public entry point that turns people's keypoints into a calibrated camera."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .calibration import Calibration, Uncertainty
from .errors import CalibrationError
from .frame import FloatArray, ImageFrame
from .frame import homogeneous
from .linear import LinearSolution, sampson_distances, solve_linear
from .ransac import RansacSettings, minimal_size, ransac
from .reconstruct import intersect_plane, place_people, rays
from .refine import Refinement, fit_camera
from .uncertainty import canonical_covariance, summarise

# Ankle-centre to shoulder-centre height of an average adult (metres): shoulder
# (acromion) height ~0.82 x stature minus ankle height ~0.07 m, for a mixed adult
# population of mean stature ~1.69 m. The paper's simulations use 1.7.
DEFAULT_HEIGHT_M = 1.32
# Spread of that height across adults (metres): the prior's std in the refinement.
DEFAULT_HEIGHT_STD_M = 0.08
# Points further outside the image than this many image sizes are rejected as absurd.
_OUTSIDE_MARGIN = 1.0


def _as_points(name: str, values: ArrayLike) -> FloatArray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{name} must be an (N, 2) array of numbers: {exc}") from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise CalibrationError(f"{name} must have shape (N, 2), got {arr.shape}")
    return arr


def validate_keypoints(
    tops: ArrayLike, bottoms: ArrayLike, image_size: tuple[float, float], height: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Checked float arrays and a mask of people with a usable (non-zero-length) segment.

    Non-finite or absurd input is an error of the caller, so it raises rather
    than being dropped silently; a zero-length segment is a person that carries
    no information, so it is only excluded.
    """
    tops_px, bottoms_px = _as_points("tops", tops), _as_points("bottoms", bottoms)
    if tops_px.shape != bottoms_px.shape:
        raise CalibrationError(f"tops and bottoms differ in shape: {tops_px.shape} vs {bottoms_px.shape}")
    if not (np.isfinite(height) and height > 0):
        raise CalibrationError(f"height must be a positive number of metres, got {height!r}")
    try:
        width, img_h = float(image_size[0]), float(image_size[1])
    except (TypeError, ValueError, IndexError):
        raise CalibrationError(f"image_size must be (width, height), got {image_size!r}") from None
    if not (np.isfinite(width) and np.isfinite(img_h) and width > 0 and img_h > 0):
        raise CalibrationError(f"image_size must be two positive numbers, got {image_size!r}")
    for name, arr in (("tops", tops_px), ("bottoms", bottoms_px)):
        bad = ~np.all(np.isfinite(arr), axis=1)
        if bad.any():
            raise CalibrationError(f"{name}[{int(np.flatnonzero(bad)[0])}] is not finite")
        lo = -_OUTSIDE_MARGIN * np.array([width, img_h])
        hi = (1 + _OUTSIDE_MARGIN) * np.array([width, img_h])
        far = np.any((arr < lo) | (arr > hi), axis=1)
        if far.any():
            i = int(np.flatnonzero(far)[0])
            raise CalibrationError(f"{name}[{i}] = {arr[i].tolist()} lies far outside the {width:g}x{img_h:g} image")
    length = np.linalg.norm(tops_px - bottoms_px, axis=1)
    usable = length > 1e-6 * (width + img_h)
    return tops_px, bottoms_px, usable


def calibrate(
    tops: ArrayLike,
    bottoms: ArrayLike,
    image_size: tuple[float, float],
    height: float = DEFAULT_HEIGHT_M,
    *,
    equal_focal: bool = True,
    robust: bool | None = None,
    refine: bool | None = None,
    seed: int | None = 0,
    principal_point: tuple[float, float] | None = None,
    focal_px: float | tuple[float, float] | None = None,
    inlier_px: float | None = None,
    height_tolerance: float = 0.3,
    max_iterations: int = 5000,
    height_std: float = DEFAULT_HEIGHT_STD_M,
) -> Calibration:
    """Calibrate a camera from people's shoulder-centre (tops) and ankle-centre (bottoms) pixels.

    height is the ankle-centre-to-shoulder-centre height prior in metres. With
    robust/refine left as None, the most accurate pipeline is used.
    """
    tops_px, bottoms_px, usable = validate_keypoints(tops, bottoms, image_size, height)
    frame = ImageFrame.from_size(image_size, principal_point)
    tops_n, bottoms_n = frame.normalise(tops_px), frame.normalise(bottoms_px)
    focal_n = None
    if focal_px is not None:
        f = np.broadcast_to(np.asarray(focal_px, dtype=np.float64), (2,))
        if not (np.all(np.isfinite(f)) and np.all(f > 0)):
            raise CalibrationError(f"focal_px must be positive, got {focal_px!r}")
        focal_n = (float(f[0]) / frame.scale_px, float(f[1]) / frame.scale_px)
    inliers = usable.copy()
    iterations = 0
    if robust is None or robust:
        settings = RansacSettings(
            inlier_px=default_inlier_px(image_size) if inlier_px is None else inlier_px,
            height_tolerance=height_tolerance,
            max_iterations=max_iterations,
        )
        found = ransac(
            tops_n[usable], bottoms_n[usable], height, equal_focal, focal_n, frame.scale_px, settings,
            np.random.default_rng(seed),
        )
        inliers[usable] = found.inliers
        solution: LinearSolution = found.solution
        iterations = found.iterations
    else:
        solution = solve_linear(tops_n[inliers], bottoms_n[inliers], height, equal_focal, focal_n)
    if inliers.sum() < minimal_size(equal_focal, focal_n is not None):
        raise CalibrationError("too few people agree on one camera")
    noise_n = estimate_noise_n(tops_n[inliers], bottoms_n[inliers], solution)
    _, _, start_heights = place_people(
        tops_n[inliers], bottoms_n[inliers], solution.focal_n, solution.normal, solution.rho_m, height
    )
    fit = fit_camera(
        tops_n[inliers], bottoms_n[inliers], solution, start_heights, height, height_std, noise_n,
        equal_focal, focal_n, optimise=refine is None or refine,
    )
    cov = canonical_covariance(fit.camera, fit.theta, fit.covariance, frame.scale_px)
    uncertainty = summarise(cov, noise_n * frame.scale_px)
    return _finish(frame, tops_n, bottoms_n, inliers, fit, height, iterations, uncertainty, refine is None or refine)


def estimate_noise_n(tops_n: FloatArray, bottoms_n: FloatArray, solution: LinearSolution) -> float:
    """Keypoint noise std (normalised units) from the height-free direction residuals.

    A Sampson distance is the noise projected on one direction, so its square is
    sigma^2 chi^2_1 distributed; the median (0.455 sigma^2) keeps stray outliers out.
    """
    v = np.array([solution.normal[0] * solution.focal_n[0], solution.normal[1] * solution.focal_n[1],
                  solution.normal[2]])
    d = sampson_distances(homogeneous(tops_n), homogeneous(bottoms_n), v)
    dof = max(len(d) - 2, 1)
    return max(float(np.sqrt(np.median(d * d) / 0.455 * len(d) / dof)), 1e-7)


def default_inlier_px(image_size: tuple[float, float]) -> float:
    """0.3 % of the image diagonal (6.6 px at 1080p), at least 3 px: a few times real keypoint noise."""
    return max(3.0, 0.003 * float(np.hypot(image_size[0], image_size[1])))


def _finish(
    frame: ImageFrame,
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    inliers: FloatArray,
    fit: Refinement,
    height: float,
    iterations: int,
    uncertainty: Uncertainty,
    refined: bool,
) -> Calibration:
    solution = fit.solution
    x_b, x_t, heights = place_people(tops_n, bottoms_n, solution.focal_n, solution.normal, solution.rho_m, height)
    if refined:
        # The fitted people get their maximum-likelihood positions and heights.
        x_b[inliers] = intersect_plane(rays(fit.ankles_n, solution.focal_n), solution.normal, solution.rho_m)
        heights[inliers] = fit.heights_m
        x_t[inliers] = x_b[inliers] + fit.heights_m[:, None] * solution.normal
    placed = inliers & np.all(np.isfinite(x_b), axis=1)
    x_b[~placed] = np.nan
    x_t[~placed] = np.nan
    heights[~placed] = np.nan
    return Calibration(
        fx=solution.focal_n[0] * frame.scale_px,
        fy=solution.focal_n[1] * frame.scale_px,
        cx=frame.cx_px,
        cy=frame.cy_px,
        normal=solution.normal,
        rho=solution.rho_m,
        image_size=(frame.width_px, frame.height_px),
        height_m=height,
        points_bottom=x_b,
        points_top=x_t,
        heights=heights,
        inliers=placed,
        ransac_iterations=iterations,
        refined=refined,
        uncertainty=uncertainty,
        reprojection_rms_px=fit.rms_residual * frame.scale_px,
    )
