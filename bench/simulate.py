"""Synthetic scenes with known ground truth, following the paper's protocol (Sect. 4).

A scene is a pinhole camera (optionally with OpenCV-style polynomial radial
distortion) at height rho above a ground plane, seeing people modelled as
vertical ankle-to-shoulder segments of truncated-Gaussian height, with
Gaussian pixel noise on both ends. Camera-frame conventions as everywhere in
service.geometry: x right, y down, z forward, ground N . X + rho = 0, N up.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import truncnorm

from service.geometry.camera import project
from service.geometry.vec import FloatArray

OUTLIER_KINDS = ("sitting", "bending", "stairs", "bad_detection")
__all__ = ["OUTLIER_KINDS", "Scene", "SceneConfig", "camera_normal", "draw_scene", "project", "sample_heights"]


@dataclass(frozen=True)
class SceneConfig:
    """What to draw. Ranges are (low, high), sampled uniformly per scene."""

    image_size: tuple[int, int] = (1920, 1080)
    vfov_deg: tuple[float, float] = (90.0, 90.0)
    square_pixels: bool = False  # False: fx = (W/H) fy, as in the paper's tables
    n_people: int = 20
    height_mean_m: float = 1.7
    height_std_m: float = 0.0
    height_range_m: tuple[float, float] = (1.5, 1.9)
    noise_px: float = 0.5
    camera_height_m: tuple[float, float] = (2.0, 8.0)
    pitch_deg: tuple[float, float] = (15.0, 60.0)
    # Roll magnitude, applied with a random sign. fx is unobservable at zero roll
    # (v = K N then has no x component), so the fx != fy tables keep it away from 0.
    roll_deg: tuple[float, float] = (10.0, 40.0)
    max_range_m: float = 25.0
    distortion_k: tuple[float, float] = (0.0, 0.0)  # OpenCV k1, k2 on focal-normalised radius
    outlier_fraction: float = 0.0

    @classmethod
    def paper(cls, **overrides: object) -> SceneConfig:
        """Tables 1-3 of the paper: 1920x1080, 90 deg vertical FOV, fx = (W/H) fy, 20 people."""
        return replace(cls(), **overrides)  # type: ignore[arg-type]

    @classmethod
    def surveillance(cls, **overrides: object) -> SceneConfig:
        """A typical fixed security camera: square pixels, little roll, 3-10 m up, 10-60 deg down."""
        base = cls(
            vfov_deg=(30.0, 70.0),
            square_pixels=True,
            height_std_m=0.07,
            noise_px=1.5,
            camera_height_m=(3.0, 10.0),
            pitch_deg=(10.0, 60.0),
            roll_deg=(0.0, 5.0),
            max_range_m=30.0,
        )
        return replace(base, **overrides)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Scene:
    """One drawn scene: the truth and the (noisy) pixels a pose model would report."""

    image_size: tuple[int, int]
    fx: float
    fy: float
    cx: float
    cy: float
    normal: FloatArray
    rho: float
    points_bottom: FloatArray
    points_top: FloatArray
    heights: FloatArray
    tops_px: FloatArray
    bottoms_px: FloatArray
    outliers: FloatArray = field(default_factory=lambda: np.zeros(0, bool))
    distortion_k: tuple[float, float] = (0.0, 0.0)


def camera_normal(pitch_deg: float, roll_deg: float) -> FloatArray:
    """Up direction in the camera frame for a camera pitched down by pitch and rolled by roll."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    level = np.array([0.0, -np.cos(p), -np.sin(p)])
    rot = np.array([[np.cos(r), -np.sin(r), 0.0], [np.sin(r), np.cos(r), 0.0], [0.0, 0.0, 1.0]])
    return rot @ level


def _distortion_monotonic(points: FloatArray, k: tuple[float, float]) -> FloatArray:
    """Where the polynomial lens map is still increasing in radius (d r_d / d r > 0).

    Past that turning point (k1 < 0) the polynomial folds points from outside the
    field of view back into the image, which no real lens does.
    """
    r2 = (points[..., 0] ** 2 + points[..., 1] ** 2) / points[..., 2] ** 2
    return 1.0 + 3.0 * k[0] * r2 + 5.0 * k[1] * r2 * r2 > 0.0


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1])) if bounds[1] > bounds[0] else float(bounds[0])


def sample_heights(rng: np.random.Generator, config: SceneConfig, n: int) -> FloatArray:
    if config.height_std_m <= 0:
        return np.full(n, config.height_mean_m)
    lo, hi = config.height_range_m
    a = (lo - config.height_mean_m) / config.height_std_m
    b = (hi - config.height_mean_m) / config.height_std_m
    return truncnorm.rvs(a, b, loc=config.height_mean_m, scale=config.height_std_m, size=n, random_state=rng)


def draw_scene(config: SceneConfig, rng: np.random.Generator, max_attempts: int = 50) -> Scene:
    """A random scene in which every person's two points are inside the image."""
    width, height = config.image_size
    for _ in range(max_attempts):
        fy = (height / 2.0) / np.tan(np.radians(_uniform(rng, config.vfov_deg)) / 2.0)
        fx = fy if config.square_pixels else fy * width / height
        roll = _uniform(rng, config.roll_deg) * rng.choice((-1.0, 1.0))
        normal = camera_normal(_uniform(rng, config.pitch_deg), roll)
        rho = _uniform(rng, config.camera_height_m)
        placed = _place_visible_people(rng, config, fx, fy, normal, rho)
        if placed is not None:
            break
    else:
        raise RuntimeError("could not draw a scene with enough visible people; widen the configuration")
    x_b, heights = placed
    x_t = x_b + heights[:, None] * normal
    cx, cy = width / 2.0, height / 2.0
    bottoms = project(x_b, fx, fy, cx, cy, config.distortion_k)
    tops = project(x_t, fx, fy, cx, cy, config.distortion_k)
    outliers = np.zeros(config.n_people, bool)
    if config.outlier_fraction > 0:
        outliers[rng.permutation(config.n_people)[: round(config.outlier_fraction * config.n_people)]] = True
        tops, bottoms = _corrupt(rng, config, outliers, x_b, heights, normal, fx, fy, tops, bottoms)
    tops = tops + rng.normal(0.0, config.noise_px, tops.shape)
    bottoms = bottoms + rng.normal(0.0, config.noise_px, bottoms.shape)
    return Scene(
        (width, height), fx, fy, cx, cy, normal, rho, x_b, x_t, heights, tops, bottoms, outliers, config.distortion_k
    )


def _place_visible_people(
    rng: np.random.Generator, config: SceneConfig, fx: float, fy: float, normal: FloatArray, rho: float
) -> tuple[FloatArray, FloatArray] | None:
    width, height = config.image_size
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    forward /= np.linalg.norm(forward)
    side = np.cross(normal, forward)
    heights = sample_heights(rng, config, config.n_people)
    chosen: list[FloatArray] = []
    reach = config.max_range_m
    for _ in range(200):
        m = 4 * config.n_people
        a = rng.uniform(-reach, reach, m)
        b = rng.uniform(0.0, reach, m)
        keep = a * a + b * b <= reach * reach
        x_b = -rho * normal + a[:, None] * side + b[:, None] * forward
        h = heights[len(chosen) % config.n_people]
        x_t = x_b + h * normal
        ok = keep & (x_b[:, 2] > 0.3) & (x_t[:, 2] > 0.3)
        ok &= _distortion_monotonic(x_b, config.distortion_k) & _distortion_monotonic(x_t, config.distortion_k)
        for pts in (x_b, x_t):
            px = project(pts, fx, fy, width / 2.0, height / 2.0, config.distortion_k)
            ok &= (px[:, 0] >= 0) & (px[:, 0] <= width) & (px[:, 1] >= 0) & (px[:, 1] <= height)
        # Per-person heights differ: re-check each candidate with the height it will get.
        for candidate in x_b[ok]:
            i = len(chosen)
            if i == config.n_people:
                break
            top = candidate + heights[i] * normal
            px = project(np.stack((candidate, top)), fx, fy, width / 2.0, height / 2.0, config.distortion_k)
            visible = top[2] > 0.3 and bool(_distortion_monotonic(top[None], config.distortion_k)[0])
            if visible and np.all((px >= 0) & (px <= (width, height))):
                chosen.append(candidate)
        if len(chosen) == config.n_people:
            return np.array(chosen), heights
    return None


def _corrupt(
    rng: np.random.Generator,
    config: SceneConfig,
    outliers: FloatArray,
    x_b: FloatArray,
    heights: FloatArray,
    normal: FloatArray,
    fx: float,
    fy: float,
    tops: FloatArray,
    bottoms: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Turn the chosen people into the outliers a real camera sees, in equal shares of each kind."""
    width, height = config.image_size
    cx, cy = width / 2.0, height / 2.0
    tops, bottoms = tops.copy(), bottoms.copy()
    horizontal = np.cross(normal, [1.0, 0.0, 0.0])
    horizontal /= np.linalg.norm(horizontal)
    for n, i in enumerate(np.flatnonzero(outliers)):
        kind = OUTLIER_KINDS[n % len(OUTLIER_KINDS)]
        if kind == "sitting":
            top = x_b[i] + heights[i] * rng.uniform(0.5, 0.7) * normal
            tops[i] = project(top, fx, fy, cx, cy, config.distortion_k)
        elif kind == "bending":
            top = x_b[i] + heights[i] * 0.8 * normal + rng.uniform(0.4, 0.7) * rng.choice([-1, 1]) * horizontal
            tops[i] = project(top, fx, fy, cx, cy, config.distortion_k)
        elif kind == "stairs":
            lift = rng.uniform(0.6, 1.5) * normal
            bottoms[i] = project(x_b[i] + lift, fx, fy, cx, cy, config.distortion_k)
            tops[i] = project(x_b[i] + lift + heights[i] * normal, fx, fy, cx, cy, config.distortion_k)
        else:
            bottoms[i] = rng.uniform((0, 0), (width, height))
            tops[i] = bottoms[i] + rng.uniform((-150, -300), (150, -20))
    # A detector reports points inside the frame, however wrong they are.
    size = np.array([width, height], dtype=np.float64)
    return np.clip(tops, 0.0, size), np.clip(bottoms, 0.0, size)
