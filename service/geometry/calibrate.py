"""calibrate(): the public entry point that turns people's keypoints into a calibrated camera."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .calibration import Calibration
from .errors import CalibrationError
from .frame import FloatArray, ImageFrame
from .linear import LinearSolution, solve_linear
from .reconstruct import place_people

# Ankle-centre to shoulder-centre height of an average adult (metres): shoulder
# (acromion) height ~0.82 x stature minus ankle height ~0.07 m, for a mixed adult
# population of mean stature ~1.69 m. The paper's simulations use 1.7.
DEFAULT_HEIGHT_M = 1.32
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
    solution: LinearSolution = solve_linear(tops_n[inliers], bottoms_n[inliers], height, equal_focal, focal_n)
    return _finish(frame, tops_n, bottoms_n, inliers, solution, height)


def _finish(
    frame: ImageFrame,
    tops_n: FloatArray,
    bottoms_n: FloatArray,
    inliers: FloatArray,
    solution: LinearSolution,
    height: float,
) -> Calibration:
    x_b, x_t, heights = place_people(tops_n, bottoms_n, solution.focal_n, solution.normal, solution.rho_m, height)
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
    )
