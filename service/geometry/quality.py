"""What a calibration is worth: a grade from the error it predicts for a typical measurement, and what would help.

The grade answers the user's question directly: how wrong can a distance be because of the calibration? It
is the predicted 2-sigma error of a 2 m distance between two people standing at the camera's typical range
(the median distance of the people it was calibrated from), the larger of a pair side by side across the
view and a pair one behind the other, from the calibration's covariance (principal point, focal length,
ground plane, lens, population height: every prior included). The keypoint noise of the two people measured
adds to every single measurement on top (each pair's distance_std_m carries it); it is left out here because
no amount of calibration evidence removes it, and the grade is about what the evidence bought.

    good         2-sigma <= 0.4 m (20 % of 2 m): a 6 ft verdict is right with >= 97.7 % confidence for every
                 pair measured outside 1.43-2.23 m (before the two people's own keypoint noise)
    rough        2-sigma <= 1.0 m (50 %): distances mean something, verdicts near the threshold do not
    unreliable   anything worse, or evidence too thin or too narrow to trust its own sigma

The population's mean height alone (a 4 % prior: no image can tell a tall crowd far away from a short one
near) puts a floor of 0.16 m under every camera; with the principal point and focal length given, a
well-sampled camera reaches 0.2-0.35 m on the realistic simulator, with the image size alone 0.3-0.6 m.

Minimum evidence, whatever the predicted error (a posterior from a few people is far from Gaussian, and a
narrow spread of people leaves whole directions to the priors' shapes, not only their widths):

* at least MIN_INDIVIDUALS distinct people (individuals, not observations: one person in thirty frames is one);
* people over depth: the farthest quarter at least DEPTH_RATIO times as far as the nearest quarter;
* people across the view: their ankles in at least MIN_CELLS of the image's 3 x 3 cells.

The HTTP side only plumbs `Quality`: grade, the predicted error, the reasons and what would help (`advice`,
`people_needed`). A calibration graded unreliable should measure but not alert.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .calibration import Calibration, Grade, Quality
from .measure import measure

GOOD_2SIGMA_M = 0.4
ROUGH_2SIGMA_M = 1.0
PROBE_DISTANCE_M = 2.0
MIN_INDIVIDUALS = 15
WELL_SAMPLED_INDIVIDUALS = 30
DEPTH_RATIO = 1.5
MIN_CELLS = 4


def _probe_error_m(cal: Calibration, range_m: float) -> float:
    """Largest 2-sigma error of a 2 m pair at range_m: across the view and along it."""
    n = np.asarray(cal.normal, dtype=np.float64)
    forward = np.array([0.0, 0.0, 1.0]) - n[2] * n
    if np.linalg.norm(forward) < 1e-9:
        forward = np.array([0.0, -1.0, 0.0]) - n[1] * n
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, n)
    foot = -cal.rho * n
    centre = foot + range_m * forward
    half = 0.5 * PROBE_DISTANCE_M
    feet = np.array([centre - half * right, centre + half * right, centre - half * forward, centre + half * forward])
    heads = feet + cal.height_m * n
    camera = cal.camera
    if np.any(feet[:, 2] <= 0.1) or np.any(heads[:, 2] <= 0.1) or cal.uncertainty is None:
        return float("nan")
    calibration_only = replace(cal, uncertainty=replace(cal.uncertainty, noise_per_length=0.0))
    m = measure(calibration_only, camera.project(heads), camera.project(feet), noise_px=0.0)
    return float(2.0 * max(m.distance_std_m[0, 1], m.distance_std_m[2, 3]))


def assess(cal: Calibration) -> Quality:
    """The grade of a calibration and what would help (see the module docstring)."""
    placed = np.asarray(cal.inliers, dtype=bool) & np.all(np.isfinite(cal.points_bottom), axis=1)
    points = np.asarray(cal.points_bottom)[placed]
    n = np.asarray(cal.normal, dtype=np.float64)
    # The placed points lie on the plane, so X + rho N is their offset from the point below the camera.
    ranges = np.linalg.norm(points + cal.rho * n, axis=1)
    typical = float(np.median(ranges)) if len(ranges) else float("nan")
    error = _probe_error_m(cal, typical) if np.isfinite(typical) and cal.uncertainty is not None else float("nan")
    reasons: list[str] = []
    advice: list[str] = []
    individuals = cal.individuals or int(placed.sum())
    thin = individuals < MIN_INDIVIDUALS
    if thin:
        reasons.append(f"only {individuals} distinct people (at least {MIN_INDIVIDUALS} are needed)")
    narrow_depth = len(ranges) >= 4 and np.percentile(ranges, 87.5) < DEPTH_RATIO * np.percentile(ranges, 12.5)
    if narrow_depth:
        reasons.append("the people stand at nearly one distance from the camera")
        advice.append("people spread over depth: near the camera and far from it")
    cells = _cells(cal, placed)
    if cells < MIN_CELLS:
        reasons.append(f"the people cover {cells} of the image's 9 regions")
        advice.append("people across the view: left, right, near and far")
    if not np.isfinite(error):
        reasons.append("the calibration has no uncertainty to predict an error from")
        grade: Grade = "unreliable"
    elif thin or narrow_depth or cells < MIN_CELLS or error > ROUGH_2SIGMA_M:
        grade = "unreliable"
    elif error > GOOD_2SIGMA_M:
        grade = "rough"
    else:
        grade = "good"
    if np.isfinite(error) and error > GOOD_2SIGMA_M:
        reasons.append(f"a 2 m distance at {typical:.0f} m is uncertain by +-{error:.2f} m (2 sigma)")
        if cal.principal_point_source != "given" or cal.focal_source != "given":
            advice.append("the camera's known intrinsics: principal point and focal length")
    needed = max(0, WELL_SAMPLED_INDIVIDUALS - individuals)
    if needed and grade != "good":
        advice.insert(0, f"more people: about {needed} more distinct people")
    return Quality(grade, error, typical, tuple(reasons), tuple(advice), needed)


def _cells(cal: Calibration, placed: np.ndarray) -> int:
    """How many of the image's 3 x 3 cells hold a placed person's ankle."""
    pts = np.asarray(cal.points_bottom)[placed]
    if not len(pts):
        return 0
    px = cal.camera.project(pts)
    w, h = cal.image_size
    col = np.clip((px[:, 0] / w * 3).astype(int), 0, 2)
    row = np.clip((px[:, 1] / h * 3).astype(int), 0, 2)
    return len(np.unique(row * 3 + col))
