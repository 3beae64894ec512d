"""calibrate(): the public entry point that turns people's keypoints into a calibrated camera."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from .calibration import Calibration
from .camera import ImageFrame, rays, undistort
from .consensus import ConsensusSettings, find_consensus, vanishing_points
from .distortion import estimate_division_k
from .errors import CalibrationError
from .linear import LinearSolution, sampson_distances, solve_linear
from .minimal import minimal_size
from .problem import CalibrationProblem, SolveOptions
from .ransac import RansacOptions
from .reconstruct import intersect_plane, place_people
from .refine import Refinement, fit_camera
from .uncertainty import canonical_covariance, summarise
from .vec import FloatArray, homogeneous

# Floor of the keypoint noise estimate, as a fraction of the image diagonal
# (0.04 px at 1080p). No pose model is better than this; it keeps the
# likelihood well conditioned on perfect synthetic input. Relative, so that
# scaling an image and its points changes nothing but f.
MIN_NOISE_FRACTION = 2e-5
# Focal lengths outside this many image widths are treated as a failed solve
# (0.05: a > 170 deg fisheye; 50: a > 1000 mm lens on a full-frame sensor).
_FOCAL_RANGE = (0.05, 50.0)
# A solve whose own 1-sigma focal uncertainty exceeds this fraction of f has not
# determined the camera (e.g. a wrong RANSAC consensus, or every person at one
# depth); it is refused rather than reported.
MAX_RELATIVE_FOCAL_STD = 0.5
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
    tops: ArrayLike, bottoms: ArrayLike, image_size: tuple[float, float]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Checked float arrays and a mask of people with a usable (non-zero-length) segment.

    Non-finite or absurd input is an error of the caller, so it raises rather
    than being dropped silently; a zero-length segment is a person that carries
    no information, so it is only excluded.
    """
    tops_px, bottoms_px = _as_points("tops", tops), _as_points("bottoms", bottoms)
    if tops_px.shape != bottoms_px.shape:
        raise CalibrationError(f"tops and bottoms differ in shape: {tops_px.shape} vs {bottoms_px.shape}")
    width, img_h = float(image_size[0]), float(image_size[1])
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
    tops: ArrayLike, bottoms: ArrayLike, problem: CalibrationProblem, options: SolveOptions | None = None
) -> Calibration:
    """Calibrate a camera from people's shoulder-centre (tops) and ankle-centre (bottoms) pixels."""
    options = SolveOptions() if options is None else options
    tops_px, bottoms_px, usable = validate_keypoints(tops, bottoms, problem.image_size_px)
    height, height_std, equal_focal = problem.height_m, problem.height_std_m, problem.equal_focal
    frame = ImageFrame.from_size(problem.image_size_px, problem.principal_point_px)
    tops_n, bottoms_n = frame.normalise(tops_px), frame.normalise(bottoms_px)
    known = problem.known_focal_px
    focal_n = None if known is None else (known[0] / frame.scale_px, known[1] / frame.scale_px)
    inlier_px = default_inlier_px(problem.image_size_px) if options.inlier_px is None else options.inlier_px
    settings = ConsensusSettings(
        inlier_px=inlier_px,
        height_tolerance=options.height_tolerance,
        ransac=RansacOptions(max_iterations=options.max_iterations),
    )
    use_ransac = options.robust is None or options.robust
    inliers, solution, iterations = _consensus(
        tops_n, bottoms_n, usable, height, equal_focal, focal_n, frame.scale_px, settings, use_ransac, options.seed
    )
    distortion_k = 0.0
    if options.distortion:
        # k from the people the pinhole model already accepts (outliers would bend it),
        # then the whole pipeline again on undistorted points.
        distortion_k = estimate_division_k(tops_n[inliers], bottoms_n[inliers], height).k
        if distortion_k != 0.0:
            tops_n, bottoms_n = undistort(tops_n, distortion_k), undistort(bottoms_n, distortion_k)
            usable &= np.all(np.isfinite(tops_n), axis=1) & np.all(np.isfinite(bottoms_n), axis=1)
            inliers, solution, iterations = _consensus(
                tops_n,
                bottoms_n,
                usable,
                height,
                equal_focal,
                focal_n,
                frame.scale_px,
                settings,
                use_ransac,
                options.seed,
            )
    if inliers.sum() < minimal_size(equal_focal, focal_n is not None):
        raise CalibrationError("too few people agree on one camera")
    optimise = options.refine is None or options.refine
    fit = None
    if optimise or options.uncertainty:
        noise_floor_n = MIN_NOISE_FRACTION * frame.diagonal_px / frame.scale_px
        noise_n = max(estimate_noise_n(tops_n[inliers], bottoms_n[inliers], solution), noise_floor_n)
        _, _, start_heights = place_people(
            tops_n[inliers], bottoms_n[inliers], solution.focal_n, solution.normal, solution.rho_m, height
        )
        fit = fit_camera(
            tops_n[inliers],
            bottoms_n[inliers],
            solution,
            start_heights,
            height,
            height_std,
            noise_n,
            equal_focal,
            focal_n,
            optimise=optimise,
        )
        if optimise and options.robust is not False:
            fit, inliers = _reject_misfits(fit, tops_n, bottoms_n, inliers, height, height_std, equal_focal, focal_n)
        solution = fit.solution
    cal = _finish(frame, tops_n, bottoms_n, inliers, solution, fit if optimise else None, height, iterations)
    cal = replace(cal, distortion_k=distortion_k)
    if fit is not None and options.uncertainty:
        cov = canonical_covariance(fit.camera, fit.theta, fit.covariance, frame.scale_px)
        cal = replace(
            cal,
            uncertainty=summarise(cov, fit.noise_n * frame.scale_px),
            reprojection_rms_px=fit.rms_residual * frame.scale_px,
        )
    check_plausible(cal, minimal_size(equal_focal, focal_n is not None))
    return cal


def check_plausible(cal: Calibration, minimum_people: int) -> None:
    """Refuse results no real camera could produce, rather than return them."""
    longest = max(cal.image_size)
    for name, f in (("fx", cal.fx), ("fy", cal.fy)):
        if not (np.isfinite(f) and _FOCAL_RANGE[0] * longest <= f <= _FOCAL_RANGE[1] * longest):
            raise CalibrationError(f"implausible focal length {name} = {f:.4g} px for a {longest:g} px wide image")
    if not (np.isfinite(cal.rho) and cal.rho > 0 and np.all(np.isfinite(cal.normal))):
        raise CalibrationError("no finite ground plane below the camera")
    if cal.num_inliers < minimum_people:
        raise CalibrationError(f"only {cal.num_inliers} people could be placed on the ground plane")
    unc = cal.uncertainty
    if unc is not None and max(unc.fx_px / cal.fx, unc.fy_px / cal.fy) > MAX_RELATIVE_FOCAL_STD:
        raise CalibrationError(
            f"the people seen do not determine the focal length (fx = {cal.fx:.0f} +- {unc.fx_px:.0f} px); "
            "more people, spread over the view and over distances, are needed"
        )


# A person whose whitened residual cost exceeds this (chi^2 with 2 degrees of
# freedom: 5 residuals minus 3 own parameters, p = 0.999) is not explained by the
# camera and is dropped before the final fit.
_CHI2_2DOF_999 = 13.8
_CHI2_2DOF_MEDIAN = 1.386


def _reject_misfits(
    fit: Refinement,
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    inliers: FloatArray,
    height: float,
    height_std: float,
    equal_focal: bool,
    focal_n: tuple[float, float] | None,
) -> tuple[Refinement, FloatArray]:
    """Second, likelihood-based inlier test after the ML fit; refit once without the misfits.

    RANSAC's tests are coarse (fixed tolerances); the fitted model knows each
    person's expected residual, so mild outliers that slipped through (people
    on a step, leaning) stand out here. The cut scales with the median cost so a
    misjudged noise level cannot make it reject everyone.
    """
    cost = fit.person_costs
    cut = _CHI2_2DOF_999 * max(float(np.median(cost)) / _CHI2_2DOF_MEDIAN, 1.0)
    keep = cost <= cut
    if keep.all() or keep.sum() < max(minimal_size(equal_focal, focal_n is not None), 0.5 * len(keep)):
        return fit, inliers
    subset = np.flatnonzero(inliers)[keep]
    refit = fit_camera(
        tops_n[subset],
        bottoms_n[subset],
        fit.solution,
        fit.heights_m[keep],
        height,
        height_std,
        fit.noise_n,
        equal_focal,
        focal_n,
    )
    narrowed = np.zeros_like(inliers)
    narrowed[subset] = True
    return refit, narrowed


def _consensus(
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    usable: FloatArray,
    height: float,
    equal_focal: bool,
    focal_n: tuple[float, float] | None,
    scale_px: float,
    settings: ConsensusSettings,
    use_ransac: bool,
    seed: int | None,
) -> tuple[FloatArray, LinearSolution, int]:
    """(inlier mask over all people, linear solution, RANSAC draws) for the usable people."""
    inliers = usable.copy()
    if not use_ransac:
        return inliers, solve_linear(tops_n[usable], bottoms_n[usable], height, equal_focal, focal_n), 0
    found = find_consensus(
        tops_n[usable],
        bottoms_n[usable],
        height,
        equal_focal,
        focal_n,
        scale_px,
        settings,
        np.random.default_rng(seed),
    )
    inliers[usable] = found.inliers
    return inliers, found.solution, found.iterations


def estimate_noise_n(tops_n: FloatArray, bottoms_n: FloatArray, solution: LinearSolution) -> float:
    """Keypoint noise std (normalised units) from the height-free direction residuals.

    A Sampson distance is the noise projected on one direction, so its square is
    sigma^2 chi^2_1 distributed; the median (0.455 sigma^2) keeps stray outliers out.
    """
    v = vanishing_points(np.asarray(solution.focal_n), solution.normal)
    d = sampson_distances(homogeneous(tops_n), homogeneous(bottoms_n), v)
    dof = max(len(d) - 2, 1)
    return float(np.sqrt(np.median(d * d) / 0.455 * len(d) / dof))


def default_inlier_px(image_size: tuple[float, float]) -> float:
    """0.3 % of the image diagonal (6.6 px at 1080p): a few times real keypoint noise.

    Relative to the image, not absolute, so calibration is invariant to image scaling.
    """
    return 0.003 * float(np.hypot(image_size[0], image_size[1]))


def _finish(
    frame: ImageFrame,
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    inliers: FloatArray,
    solution: LinearSolution,
    fit: Refinement | None,
    height: float,
    iterations: int,
) -> Calibration:
    x_b, x_t, heights = place_people(tops_n, bottoms_n, solution.focal_n, solution.normal, solution.rho_m, height)
    if fit is not None:
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
        refined=fit is not None,
    )
