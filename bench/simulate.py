"""Synthetic scenes with known ground truth, following the paper's protocol (Sect. 4), and real cameras' mismatches.

A scene is a pinhole camera (optionally with OpenCV-style polynomial radial
distortion) at height rho above a ground plane, seeing people modelled as
vertical ankle-to-shoulder segments of truncated-Gaussian height, with
Gaussian pixel noise on both ends. Camera-frame conventions as everywhere in
service.geometry: x right, y down, z forward, ground N . X + rho = 0, N up.

`SceneConfig.realistic` adds what real cameras and pose models bring (issue 16), each off by default:
a principal point up to 15 % of the image height off centre, fy/fx up to 2 % from 1, wide-angle barrel
distortion, a crowd whose mean height is up to 4 % off the prior, a per-camera keypoint bias along the body
(a constant pixel offset of the shoulder keypoint), ankle keypoints above the ground, walking people's lean,
keypoint noise that grows with a person's size, and individuals seen in several frames along a short walk
(one height each). Every extra draw happens only when its feature is on, so the paper's scenes are unchanged.
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
    # Real cameras' mismatches (see the module docstring); all off by default.
    principal_offset_frac: float = 0.0  # |pp - centre| up to this x image height, uniform over the disc
    aspect_range: float = 0.0  # fy / fx = 1 + U(-a, a)
    distortion_corner: tuple[float, float] = (0.0, 0.0)  # barrel: the image corner moves in by U(lo, hi) of its radius
    population_mean_frac: float = 0.0  # the crowd's mean height = height_mean_m (1 + U(-p, p))
    keypoint_bias_px: float = 0.0  # shoulder keypoint offset along the body, U(-b, b) px per 1080 px of image height
    ankle_height_m: float = 0.0  # ankle keypoints this far above the ground (scaled with each person's height)
    lean_deg: float = 0.0  # frame-to-frame sway of the ankle-to-shoulder axis, N(0, lean) degrees per axis
    forward_lean_deg: float = 0.0  # walkers' own forward lean along their walk, N(f, f / 2) degrees, kept
    noise_rel: float = 0.0  # keypoint noise std = hypot(noise_px, noise_rel x segment length)
    observations_per_person: int = 1  # each individual seen this many times along a short walk
    walk_step_m: float = 0.7  # ground distance between an individual's sightings (0.7 m: 0.5 s at walking pace)

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

    @classmethod
    def realistic(cls, **overrides: object) -> SceneConfig:
        """The surveillance preset with every real-camera mismatch of issue 16 (see the module docstring).

        Heights are the ankle-centre-to-shoulder-centre segment of the geometry's default prior (1.32 m, spread
        0.08 m), so a solver given that prior meets the crowd's mean only up to the drawn population offset.
        """
        base = cls.surveillance(
            n_people=120,
            height_mean_m=1.32,
            height_std_m=0.08,
            height_range_m=(1.05, 1.6),
            noise_px=1.5,
            principal_offset_frac=0.15,
            aspect_range=0.02,
            distortion_corner=(0.0, 0.06),
            population_mean_frac=0.04,
            keypoint_bias_px=2.0,
            ankle_height_m=0.07,
            lean_deg=2.0,
            forward_lean_deg=1.0,
            noise_rel=0.01,
            observations_per_person=4,
        )
        return replace(base, **overrides)  # type: ignore[arg-type]

    @classmethod
    def wide_angle(cls, **overrides: object) -> SceneConfig:
        """The realistic preset through an indoor wide-angle lens: 60-90 deg vertically, a barrel lens moving the
        image corner in by 3-15 % of its radius (rectilinear wide lenses bend more: service.geometry.problem), the
        camera 2.5-6 m up over people within 20 m."""
        base = cls.realistic(
            vfov_deg=(60.0, 90.0), distortion_corner=(0.03, 0.15), camera_height_m=(2.5, 6.0), max_range_m=20.0
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
    # Which individual each observation is (equal labels: one person seen in several frames).
    tracks: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    ankle_height_m: float = 0.0  # mean height of the ankle keypoints above the ground (rho is to the ground)


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


@dataclass(frozen=True)
class _Camera:
    fx: float
    fy: float
    cx: float
    cy: float
    normal: FloatArray
    rho: float
    k: tuple[float, float]

    def project(self, points: FloatArray) -> FloatArray:
        return project(points, self.fx, self.fy, self.cx, self.cy, self.k)

    def sees(self, points: FloatArray, size: tuple[int, int]) -> FloatArray:
        """(n,) whether each point is in front, on the lens's monotone range and inside the image."""
        ok = (points[..., 2] > 0.3) & _distortion_monotonic(points, self.k)
        px = self.project(points)
        return ok & np.all((px >= 0) & (px <= size), axis=-1)


def _draw_camera(config: SceneConfig, rng: np.random.Generator) -> _Camera:
    width, height = config.image_size
    fy = (height / 2.0) / np.tan(np.radians(_uniform(rng, config.vfov_deg)) / 2.0)
    fx = fy if config.square_pixels else fy * width / height
    roll = _uniform(rng, config.roll_deg) * rng.choice((-1.0, 1.0))
    normal = camera_normal(_uniform(rng, config.pitch_deg), roll)
    rho = _uniform(rng, config.camera_height_m)
    cx, cy = width / 2.0, height / 2.0
    k = config.distortion_k
    if config.principal_offset_frac > 0:
        radius = config.principal_offset_frac * height * np.sqrt(rng.uniform())
        angle = rng.uniform(0, 2 * np.pi)
        cx, cy = cx + radius * np.cos(angle), cy + radius * np.sin(angle)
    if config.aspect_range > 0:
        fy = fx * (1.0 + rng.uniform(-config.aspect_range, config.aspect_range))
    corner = _uniform(rng, config.distortion_corner)
    if corner > 0:
        r2 = (width / 2.0 / fx) ** 2 + (height / 2.0 / fy) ** 2
        k = (-corner / r2, 0.0)
    return _Camera(fx, fy, cx, cy, normal, rho, k)


def draw_scene(config: SceneConfig, rng: np.random.Generator, max_attempts: int = 50) -> Scene:
    """A random scene in which every person's two points are inside the image."""
    width, height = config.image_size
    for _ in range(max_attempts):
        camera = _draw_camera(config, rng)
        placed = _place_visible_people(rng, config, camera)
        if placed is not None:
            break
    else:
        raise RuntimeError("could not draw a scene with enough visible people; widen the configuration")
    x_b, heights, tracks, upright = placed
    x_t = x_b + heights[:, None] * upright
    bottoms = camera.project(x_b)
    tops = camera.project(x_t)
    if config.keypoint_bias_px > 0:
        bias = rng.uniform(-1.0, 1.0) * config.keypoint_bias_px * height / 1080.0
        along = tops - bottoms
        tops = tops + bias * along / np.linalg.norm(along, axis=1, keepdims=True)
    outliers = np.zeros(config.n_people, bool)
    if config.outlier_fraction > 0:
        outliers[rng.permutation(config.n_people)[: round(config.outlier_fraction * config.n_people)]] = True
        tops, bottoms = _corrupt(rng, config, outliers, x_b, heights, camera, tops, bottoms)
    noise_top = noise_bottom = np.full((config.n_people, 1), config.noise_px)
    if config.noise_rel > 0:
        length = np.linalg.norm(tops - bottoms, axis=1, keepdims=True)
        noise_top = noise_bottom = np.hypot(config.noise_px, config.noise_rel * length)
    tops = tops + rng.normal(0.0, 1.0, tops.shape) * noise_top
    bottoms = bottoms + rng.normal(0.0, 1.0, bottoms.shape) * noise_bottom
    return Scene(
        (width, height),
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.normal,
        camera.rho,
        x_b,
        x_t,
        heights,
        tops,
        bottoms,
        outliers,
        camera.k,
        tracks,
        config.ankle_height_m,
    )


def _place_visible_people(
    rng: np.random.Generator, config: SceneConfig, camera: _Camera
) -> tuple[FloatArray, FloatArray, np.ndarray, FloatArray] | None:
    """(ankle points, heights, individual of each observation, each body's up direction) or None.

    An individual seen several times walks a straight line from a visible start; the observations that
    leave the view are dropped, so some individuals are seen fewer times.
    """
    normal, rho, n = camera.normal, camera.rho, config.n_people
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    forward /= np.linalg.norm(forward)
    side = np.cross(normal, forward)
    per_person = max(config.observations_per_person, 1)
    heights = sample_heights(rng, config, n)
    if config.population_mean_frac > 0:
        heights = heights * (1.0 + rng.uniform(-config.population_mean_frac, config.population_mean_frac))
    chosen: list[FloatArray] = []
    owner: list[int] = []
    headings: list[FloatArray | None] = []
    reach = config.max_range_m
    for _ in range(200):
        m = 4 * n
        a = rng.uniform(-reach, reach, m)
        b = rng.uniform(0.0, reach, m)
        keep = a * a + b * b <= reach * reach
        x_b = -rho * normal + a[:, None] * side + b[:, None] * forward
        person = owner[-1] + 1 if owner else 0
        ok = (
            keep
            & camera.sees(x_b, config.image_size)
            & camera.sees(x_b + heights[person % n] * normal, config.image_size)
        )
        # Per-person heights differ: re-check each candidate with the height it will get.
        for candidate in x_b[ok]:
            if len(owner) == n:
                break
            person = owner[-1] + 1 if owner else 0
            walk, heading = (
                _walk(rng, candidate, normal, per_person, config.walk_step_m)
                if per_person > 1
                else (candidate[None], None)
            )
            top = walk + heights[person] * normal
            seen = camera.sees(walk, config.image_size) & camera.sees(top, config.image_size)
            for point in walk[seen][: n - len(owner)]:
                chosen.append(point)
                owner.append(person)
                headings.append(heading)
        if len(owner) == n:
            labels = np.array(owner)
            h = heights[labels]
            x_b = np.array(chosen) + config.ankle_height_m * (h / config.height_mean_m)[:, None] * normal
            return x_b, h, labels, _lean(rng, config, normal, labels, headings)
    return None


def _walk(
    rng: np.random.Generator, start: FloatArray, normal: FloatArray, count: int, step_m: float
) -> tuple[FloatArray, FloatArray]:
    """count ground points step_m apart (the walk between sampled frames) in a random direction, and that
    direction."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    angle = rng.uniform(0, 2 * np.pi)
    direction = np.cos(angle) * e1 + np.sin(angle) * e2
    return start + step_m * np.arange(count)[:, None] * direction, direction


def _lean(
    rng: np.random.Generator,
    config: SceneConfig,
    normal: FloatArray,
    labels: np.ndarray,
    headings: list[FloatArray | None],
) -> FloatArray:
    """(n, 3) unit up-directions of people's bodies. A walker leans forward, along their walking direction, by
    their own N(forward, forward / 2) degrees, kept from frame to frame, and sways by N(0, lean) per axis from
    frame to frame (the ankle centre swings about the pelvis through the gait cycle); people seen once lean
    forward in a random direction. The ankle-centre-to-shoulder-centre axis leans less than the trunk: a
    3 degree trunk lean over its 0.5 m moves the shoulders ~2.5 cm, about 1 degree of the 1.3 m segment."""
    n = len(labels)
    if config.lean_deg <= 0 and config.forward_lean_deg <= 0:
        return np.broadcast_to(normal, (n, 3)).copy()
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    forward = rng.normal(config.forward_lean_deg, config.forward_lean_deg / 2.0, int(labels.max()) + 1)[labels]
    sway = rng.normal(0.0, config.lean_deg, (n, 2))
    up = np.empty((n, 3))
    for i, heading in enumerate(headings):
        if heading is None:
            angle = rng.uniform(0, 2 * np.pi)
            heading = np.cos(angle) * e1 + np.sin(angle) * e2
        tilt = np.tan(np.radians(forward[i])) * heading + np.tan(np.radians(sway[i, 0])) * e1
        up[i] = normal + tilt + np.tan(np.radians(sway[i, 1])) * e2
    return up / np.linalg.norm(up, axis=1, keepdims=True)


def _corrupt(
    rng: np.random.Generator,
    config: SceneConfig,
    outliers: FloatArray,
    x_b: FloatArray,
    heights: FloatArray,
    camera: _Camera,
    tops: FloatArray,
    bottoms: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Turn the chosen people into the outliers a real camera sees, in equal shares of each kind."""
    width, height = config.image_size
    normal = camera.normal
    tops, bottoms = tops.copy(), bottoms.copy()
    horizontal = np.cross(normal, [1.0, 0.0, 0.0])
    horizontal /= np.linalg.norm(horizontal)
    for n, i in enumerate(np.flatnonzero(outliers)):
        kind = OUTLIER_KINDS[n % len(OUTLIER_KINDS)]
        if kind == "sitting":
            top = x_b[i] + heights[i] * rng.uniform(0.5, 0.7) * normal
            tops[i] = camera.project(top)
        elif kind == "bending":
            top = x_b[i] + heights[i] * 0.8 * normal + rng.uniform(0.4, 0.7) * rng.choice([-1, 1]) * horizontal
            tops[i] = camera.project(top)
        elif kind == "stairs":
            lift = rng.uniform(0.6, 1.5) * normal
            bottoms[i] = camera.project(x_b[i] + lift)
            tops[i] = camera.project(x_b[i] + lift + heights[i] * normal)
        else:
            bottoms[i] = rng.uniform((0, 0), (width, height))
            tops[i] = bottoms[i] + rng.uniform((-150, -300), (150, -20))
    # A detector reports points inside the frame, however wrong they are.
    size = np.array([width, height], dtype=np.float64)
    return np.clip(tops, 0.0, size), np.clip(bottoms, 0.0, size)
