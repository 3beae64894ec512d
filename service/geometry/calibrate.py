"""calibrate(): the public entry point that turns people's keypoints into a calibrated camera.

The pipeline: check the input; undistort the keypoints with the user's lens, if given; RANSAC over
minimal samples of people (consensus.py) for a starting camera and the inliers; lens distortion where the
evidence supports it (distortion.py); the noise model and the MAP fit with the nuisances people cannot
determine (posterior.py, refine.py, model.py); the placement of every person; plausibility checks.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from .calibration import Calibration, Source, Uncertainty
from .camera import Camera, ImageFrame, rays, undistort
from .consensus import ConsensusSettings, find_consensus
from .distortion import corner_shift_n, estimate_division_k
from .errors import CalibrationError
from .linear import LinearSolution, solve_linear
from .minimal import minimal_size
from .model import Layout, Priors
from .posterior import (
    MIN_NOISE_FRACTION,
    NoiseModel,
    Posterior,
    canonical_covariance,
    direction_residuals_n,
    estimate_noise,
    estimate_noise_and_lean,
    fit_posterior,
    with_groups,
)
from .problem import CalibrationProblem, SolveOptions
from .quality import assess
from .ransac import RansacOptions
from .reconstruct import intersect_plane, place_people
from .uncertainty import summarise
from .vec import FloatArray

# Focal lengths outside this many image widths are treated as a failed solve
# (0.05: a > 170 deg fisheye; 50: a > 1000 mm lens on a full-frame sensor).
_FOCAL_RANGE = (0.05, 50.0)
# Points further outside the image than this many image sizes are rejected as absurd.
_OUTSIDE_MARGIN = 1.0
# A solve whose own 1-sigma focal uncertainty exceeds this fraction of f has not
# determined the camera (e.g. a wrong RANSAC consensus, or every person at one
# depth); it is refused rather than reported.
MAX_RELATIVE_FOCAL_STD = 0.5
# Below this many distinct people a focal length is reported only when they pin it to FEW_PEOPLE_FOCAL_STD: a
# handful of people leaves the posterior so far from Gaussian that a wide sigma means nothing (4 people at
# 3 px noise: f = 161 +- 72 px for a true 540), and RANSAC has no redundancy to reject one bad detection.
# Between this and service.geometry.quality's thresholds a calibration is reported but graded unreliable.
MIN_INDIVIDUALS_FOR_FOCAL = 5
FEW_PEOPLE_FOCAL_STD = 0.1
# An estimated lens must move the image corner by more than this many keypoint-noise sigmas to be kept: a
# distortion smaller than the noise changes nothing measurable and only adds a parameter.
_MATERIAL_LENS_SIGMAS = 1.0
_LENS_TEST_PEOPLE = 600
# A lens is estimated only from this many agreeing people: with fewer the test has no power and a fitted k
# mostly fits noise (three people even determine k exactly, whatever the lens).
_MIN_LENS_PEOPLE = 20
_LENS_FOCAL_ROUNDS = 5


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


def _tracks(tracks: ArrayLike | None, n: int) -> np.ndarray:
    if tracks is None:
        return np.arange(n)
    labels = np.asarray(tracks)
    if labels.shape != (n,):
        raise CalibrationError(f"tracks must hold one label per person ({n}), got shape {labels.shape}")
    return np.unique(labels, return_inverse=True)[1].ravel()


@dataclass(frozen=True)
class _Stage:
    """The camera as far as it is solved: normalised points, inliers, linear solution, lens."""

    frame: ImageFrame
    raw_tops_n: FloatArray  # measured, normalised
    raw_bottoms_n: FloatArray
    tops_n: FloatArray  # undistorted by k
    bottoms_n: FloatArray
    usable: FloatArray
    inliers: FloatArray
    solution: LinearSolution
    iterations: int
    k: float = 0.0


def _consensus(
    frame: ImageFrame,
    tops_px: FloatArray,
    bottoms_px: FloatArray,
    usable: FloatArray,
    problem: CalibrationProblem,
    options: SolveOptions,
    focal_n: tuple[float, float] | None,
    k: float = 0.0,
) -> _Stage:
    """RANSAC (or the batch solve) on the usable people, after undistorting by k."""
    raw_tops_n, raw_bottoms_n = frame.normalise(tops_px), frame.normalise(bottoms_px)
    tops_n, bottoms_n = raw_tops_n, raw_bottoms_n
    if k != 0.0:
        tops_n, bottoms_n = undistort(tops_n, k), undistort(bottoms_n, k)
        usable = usable & np.all(np.isfinite(tops_n), axis=1) & np.all(np.isfinite(bottoms_n), axis=1)
    inliers = usable.copy()
    h, eq = problem.height_m, problem.equal_focal
    points = (frame, raw_tops_n, raw_bottoms_n, tops_n, bottoms_n, usable, inliers)
    if options.robust is False:
        return _Stage(*points, solve_linear(tops_n[usable], bottoms_n[usable], h, eq, focal_n), 0, k)
    settings = ConsensusSettings(
        inlier_px=default_inlier_px(problem.image_size_px) if options.inlier_px is None else options.inlier_px,
        height_tolerance=options.height_tolerance,
        ransac=RansacOptions(max_iterations=options.max_iterations),
    )
    found = find_consensus(
        tops_n[usable], bottoms_n[usable], h, eq, focal_n, frame.scale_px, settings, np.random.default_rng(options.seed)
    )
    inliers[usable] = found.inliers
    return _Stage(*points, found.solution, found.iterations, k)


def _undistort_with(
    tops_px: FloatArray, bottoms_px: FloatArray, problem: CalibrationProblem, focal_px: tuple[float, float]
) -> tuple[FloatArray, FloatArray]:
    """Keypoints through the inverse of the user's lens for a focal length (OpenCV's model works on
    focal-normalised coordinates). A point the lens model cannot invert (far outside its calibrated range)
    keeps its position; the consensus then judges it like any other person."""
    frame = ImageFrame.from_size(problem.image_size_px, problem.principal_point_px)
    camera = Camera(focal_px[0], focal_px[1], frame.cx_px, frame.cy_px, problem.image_size_px, lens=problem.lens)
    tops_u, bottoms_u = camera.undistort_px(tops_px), camera.undistort_px(bottoms_px)
    return np.where(np.isfinite(tops_u), tops_u, tops_px), np.where(np.isfinite(bottoms_u), bottoms_u, bottoms_px)


def _lens_focal_px(
    tops_px: FloatArray, bottoms_px: FloatArray, usable: FloatArray, problem: CalibrationProblem, options: SolveOptions
) -> tuple[float, float]:
    """The focal length to undistort a given lens with when none is known: the consensus's, on points
    undistorted with the previous estimate, to a fixed point (the undistortion depends on f only weakly)."""
    frame = ImageFrame.from_size(problem.image_size_px, problem.principal_point_px)
    points = (tops_px, bottoms_px)
    focal = (0.0, 0.0)
    for _ in range(_LENS_FOCAL_ROUNDS):
        stage = _consensus(frame, *points, usable, problem, options, None)
        new = (stage.solution.focal_n[0] * frame.scale_px, stage.solution.focal_n[1] * frame.scale_px)
        if abs(new[0] / max(focal[0], 1e-300) - 1.0) < 1e-9:
            break
        focal = new
        points = _undistort_with(tops_px, bottoms_px, problem, focal)
    return focal


def _priors(
    problem: CalibrationProblem, frame: ImageFrame, focal_n: tuple[float, float], focal_known: bool, lens_prior: bool
) -> Priors:
    h_px = float(problem.image_size_px[1])
    pp_std = problem.principal_point_std * h_px / frame.scale_px
    camera_height = None
    if problem.camera_height_m is not None:
        camera_height = (problem.camera_height_m - problem.ankle_height_m, problem.camera_height_std_m)
    corner_n = 0.5 * frame.diagonal_px / frame.scale_px
    spread = problem.lens_corner_spread(corner_n / float(np.sqrt(focal_n[0] * focal_n[1])))
    lens_std = spread / corner_n**2  # division model: the corner moves by about k r^3
    return Priors(
        principal_point_n=None if problem.principal_point_px is not None or pp_std == 0 else pp_std,
        distortion_k=None if (problem.lens is not None or lens_std == 0 or not lens_prior) else lens_std,
        aspect=None if (focal_known or problem.aspect_std == 0 or not problem.equal_focal) else problem.aspect_std,
        bias_n=None if problem.keypoint_bias_std == 0 else problem.keypoint_bias_std * h_px / frame.scale_px,
        log_mean_height=problem.mean_height_std if problem.mean_height_std > 0 else None,
        height_std_rel=problem.height_std_m / problem.height_m,
        camera_height_m=camera_height,
    )


def calibrate(
    tops: ArrayLike,
    bottoms: ArrayLike,
    problem: CalibrationProblem,
    options: SolveOptions | None = None,
    *,
    tracks: ArrayLike | None = None,
    repeats: ArrayLike | None = None,
) -> Calibration:
    """Calibrate a camera from people's shoulder-centre (tops) and ankle-centre (bottoms) pixels.

    tracks, optional, labels each observation with the individual it is (equal labels: the same person seen
    in several frames, who has one height); by default every observation is its own individual. repeats,
    optional, labels the individuals they could be (a grouping coarser than tracks: tracks.possible_repeats): the
    camera is the one fitted to `tracks`, its sigma the one with one height per such group.
    """
    options = SolveOptions() if options is None else options
    tops_px, bottoms_px, usable = validate_keypoints(tops, bottoms, problem.image_size_px)
    track = _tracks(tracks, len(tops_px))
    people = _People(track, track if repeats is None else _tracks(repeats, len(tops_px)))
    if problem.lens is None:
        return _solve(tops_px, bottoms_px, usable, people, problem, options)
    known = problem.known_focal_px
    focal = known or _lens_focal_px(tops_px, bottoms_px, usable, problem, options)
    cal = _solve(*_undistort_with(tops_px, bottoms_px, problem, focal), usable, people, problem, options)
    if known is None and abs(cal.fx / focal[0] - 1.0) > 1e-6:
        # Undistorted with the consensus's focal length; the final one differs a little: once more with it.
        cal = _solve(*_undistort_with(tops_px, bottoms_px, problem, (cal.fx, cal.fy)), usable, people, problem, options)
    return cal


@dataclass(frozen=True)
class _People:
    """Who the observations are: `track` the individuals the camera is fitted to, `repeats` those its sigma assumes."""

    track: np.ndarray
    repeats: np.ndarray


def _solve(
    tops_px: FloatArray,
    bottoms_px: FloatArray,
    usable: FloatArray,
    people: _People,
    problem: CalibrationProblem,
    options: SolveOptions,
) -> Calibration:
    """The pipeline on keypoints free of the user's lens."""
    track = people.track
    frame = ImageFrame.from_size(problem.image_size_px, problem.principal_point_px)
    known = problem.known_focal_px
    focal_n = None if known is None else (known[0] / frame.scale_px, known[1] / frame.scale_px)
    minimum = minimal_size(problem.equal_focal, focal_n is not None)
    stage = _consensus(frame, tops_px, bottoms_px, usable, problem, options, focal_n)
    noise_floor_n = MIN_NOISE_FRACTION * frame.diagonal_px / frame.scale_px
    if options.distortion and problem.lens is None and stage.inliers.sum() >= _MIN_LENS_PEOPLE:
        stage = _with_lens(stage, tops_px, bottoms_px, track, problem, options, focal_n, noise_floor_n)
    if stage.inliers.sum() < minimum:
        raise CalibrationError("too few people agree on one camera")
    optimise = options.refine is None or options.refine
    posterior = None
    if optimise or options.uncertainty:
        posterior = _posterior(stage, track, problem, options, focal_n, noise_floor_n, optimise, minimum)
        inliers = np.flatnonzero(stage.inliers)[posterior.kept]
        posterior = with_groups(posterior, people.repeats[inliers])
    cal = _finish(stage, posterior, problem, track, optimise)
    check_plausible(cal, minimum)
    return replace(cal, quality=assess(cal)) if cal.uncertainty is not None else cal


def _with_lens(
    stage: _Stage,
    tops_px: FloatArray,
    bottoms_px: FloatArray,
    track: np.ndarray,
    problem: CalibrationProblem,
    options: SolveOptions,
    focal_n: tuple[float, float] | None,
    noise_floor_n: float,
) -> _Stage:
    """The division model's k from the people the pinhole model already accepts (outliers would bend it),
    kept when it is significant and material, then the whole consensus again on undistorted points."""
    inl = np.flatnonzero(stage.inliers)
    # The test is a search over k (a few dozen Sampson fits): a spatially unbiased subsample keeps it cheap
    # on large crowds without losing a lens that bends their segments visibly.
    inl = inl[:: max(1, len(inl) // _LENS_TEST_PEOPLE)]
    try:
        k = estimate_division_k(stage.tops_n[inl], stage.bottoms_n[inl], problem.height_m, individuals=track[inl]).k
    except CalibrationError:
        return stage
    if k == 0.0:
        return stage
    noise = estimate_noise(
        direction_residuals_n(stage.tops_n[inl], stage.bottoms_n[inl], stage.solution),
        np.hypot(*(stage.tops_n[inl] - stage.bottoms_n[inl]).T),
        noise_floor_n,
    )
    corner_n = 0.5 * stage.frame.diagonal_px / stage.frame.scale_px
    if corner_shift_n(k, corner_n) <= _MATERIAL_LENS_SIGMAS * noise.sigma_n:
        return stage
    try:
        return _consensus(stage.frame, tops_px, bottoms_px, stage.usable, problem, options, focal_n, k)
    except CalibrationError:
        return stage


def _posterior(
    stage: _Stage,
    track: np.ndarray,
    problem: CalibrationProblem,
    options: SolveOptions,
    focal_n: tuple[float, float] | None,
    noise_floor_n: float,
    optimise: bool,
    minimum: int,
) -> Posterior:
    inl = stage.inliers
    tops_n, bottoms_n = stage.tops_n[inl], stage.bottoms_n[inl]
    sol = stage.solution
    noise, lean = estimate_noise_and_lean(
        direction_residuals_n(tops_n, bottoms_n, sol), np.hypot(*(tops_n - bottoms_n).T), track[inl], noise_floor_n
    )
    if not optimise:
        noise, lean = NoiseModel(noise.sigma_n, 0.0), 0.0
    priors = replace(_priors(problem, stage.frame, sol.focal_n, focal_n is not None, options.distortion), lean_rad=lean)
    layout = Layout.build(problem.equal_focal, focal_n, priors, stage.k != 0.0)
    _, _, heights = place_people(tops_n, bottoms_n, sol.focal_n, sol.normal, sol.rho_m, problem.height_m)
    # The latent ankles live in measured (distorted) coordinates: the model undistorts them itself.
    return fit_posterior(
        stage.raw_tops_n[inl],
        stage.raw_bottoms_n[inl],
        track[inl],
        layout,
        priors,
        sol,
        stage.k,
        heights,
        problem.height_m,
        noise,
        optimise=optimise,
        reject=options.robust is not False,
        minimum_people=minimum,
    )


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
    few = cal.individuals < MIN_INDIVIDUALS_FOR_FOCAL
    if unc is not None and cal.focal_source == "estimated" and few and unc.fx_px > FEW_PEOPLE_FOCAL_STD * cal.fx:
        raise CalibrationError(
            f"the people seen do not determine the focal length: {cal.individuals} distinct people agree, at "
            f"least {MIN_INDIVIDUALS_FOR_FOCAL} are needed; more people, spread over the view and over distances, "
            "or the camera's known focal length"
        )
    if unc is not None and max(unc.fx_px / cal.fx, unc.fy_px / cal.fy) > MAX_RELATIVE_FOCAL_STD:
        raise CalibrationError(
            f"the people seen do not determine the focal length (fx = {cal.fx:.0f} +- {unc.fx_px:.0f} px); "
            "more people, spread over the view and over distances, are needed"
        )


def default_inlier_px(image_size: tuple[float, float]) -> float:
    """0.3 % of the image diagonal (6.6 px at 1080p): a few times real keypoint noise.

    Relative to the image, not absolute, so calibration is invariant to image scaling.
    """
    return 0.003 * float(np.hypot(image_size[0], image_size[1]))


def _finish(
    stage: _Stage,
    posterior: Posterior | None,
    problem: CalibrationProblem,
    track: np.ndarray,
    optimise: bool,
) -> Calibration:
    """The Calibration: the fitted camera (or the linear one), everyone placed, the canonical covariance."""
    frame = stage.frame
    sol = stage.solution
    focal, normal, rho, centre, k = np.array(sol.focal_n), sol.normal, sol.rho_m, np.zeros(2), stage.k
    inliers = stage.inliers.copy()
    if posterior is not None and optimise:
        cam = posterior.problem.cameras(posterior.fit.theta)
        focal = np.array([cam.fx[0, 0], cam.fy[0, 0]])
        normal, rho, centre, k = cam.normal[0, 0], float(cam.rho[0, 0]), cam.c[0, 0], float(cam.k[0, 0])
        inliers[np.flatnonzero(inliers)[~posterior.kept]] = False
    # Everyone is placed with the final camera; the fitted people at their MAP ankles and heights.
    tops_c, bottoms_c = _centred(stage.raw_tops_n, centre, k), _centred(stage.raw_bottoms_n, centre, k)
    x_b, x_t, heights = place_people(tops_c, bottoms_c, (focal[0], focal[1]), normal, rho, problem.height_m)
    if posterior is not None and optimise:
        fit = posterior.fit
        ankles = _centred(fit.ankles_n, centre, k)
        rows = np.flatnonzero(inliers)
        x_b[rows] = intersect_plane(rays(ankles, focal), normal, rho)
        mu = float(posterior.problem.cameras(fit.theta).mu[0, 0])
        h = mu * (1.0 + fit.person[posterior.problem.observations.track, 0])
        heights[rows] = h
        x_t[rows] = x_b[rows] + h[:, None] * normal
    placed = inliers & np.all(np.isfinite(x_b), axis=1)
    x_b[~placed], x_t[~placed], heights[~placed] = np.nan, np.nan, np.nan
    uncertainty, rms_px = None, float("nan")
    if posterior is not None:
        cov = canonical_covariance(posterior.problem, posterior.fit.theta, posterior.fit.covariance, frame.scale_px)
        noise = posterior.noise
        uncertainty = summarise(cov, noise.sigma_n * frame.scale_px, noise.lean)
        r = posterior.fit.person_costs
        std = posterior.problem.observations.ankle_std_n
        rms_px = float(np.sqrt(np.mean(r / 4.0 * std**2))) * frame.scale_px
    return Calibration(
        fx=float(focal[0] * frame.scale_px),
        fy=float(focal[1] * frame.scale_px),
        cx=float(frame.cx_px + centre[0] * frame.scale_px),
        cy=float(frame.cy_px + centre[1] * frame.scale_px),
        normal=normal,
        rho=float(rho),
        image_size=(frame.width_px, frame.height_px),
        height_m=problem.height_m,
        points_bottom=x_b,
        points_top=x_t,
        heights=heights,
        inliers=placed,
        uncertainty=uncertainty,
        distortion_k=float(k),
        refined=posterior is not None and optimise,
        ransac_iterations=stage.iterations,
        reprojection_rms_px=rms_px,
        lens=problem.lens,
        ankle_height_m=problem.ankle_height_m,
        principal_point_source=_principal_point_source(problem, uncertainty),
        focal_source="given" if problem.focal_px is not None else "estimated",
        distortion_source="given" if problem.lens is not None else ("estimated" if k != 0.0 else "assumed"),
        individuals=len(np.unique(track[placed])),
    )


def _centred(points_n: FloatArray, centre: FloatArray, k: float) -> FloatArray:
    """Measured normalised points about the principal point, undistorted: what rays() takes."""
    rel = points_n - centre
    return undistort(rel, k) if k != 0.0 else rel


def _principal_point_source(problem: CalibrationProblem, uncertainty: Uncertainty | None) -> Source:
    if problem.principal_point_px is not None:
        return "given"
    prior_px = problem.principal_point_std * float(problem.image_size_px[1])
    if uncertainty is None or prior_px == 0:
        return "assumed"
    # Estimated when the people cut the prior's spread by half along both axes; otherwise the answer is the
    # prior's (the image centre) and its sigma the prior's.
    sd = max(uncertainty.cx_px, uncertainty.cy_px)
    return "estimated" if sd < 0.5 * prior_px else "assumed"
