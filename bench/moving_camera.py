"""A camera in a world of walking people whose pose can change: panned, tilted, zoomed, nudged.

bench.simulate and bench.frames draw people in the camera's own frame, which is all a fixed camera needs. A camera
that moves needs a world that stays put: here people walk on a ground plane in world coordinates (X east, Y north,
Z up, ground Z = 0) and a pinhole camera at a world position with a yaw, pitch and roll sees them. Changing the
camera's pose changes which people it sees and where, exactly as bumping a real camera would.

The crowd is what a street camera sees, not a textbook: every person has their own shoulder-over-ankle height and a
persistent lean (people, and pose models, do not stand perfectly upright), walks at their own speed and wanders;
a share of them are outliers a detector must shrug off: people sitting on benches (still, shoulders at 0.55-0.7 of
their standing height), children (0.6-0.95 m), and optionally a school class passing as one tight group. Keypoint
noise is Gaussian with a heavier tail (a few centres misplaced by a lot).

Camera-frame conventions as everywhere in service.geometry: x right, y down, z forward; the ground plane in the
camera frame is N . X + rho = 0 with N up and rho the camera's height.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from service.geometry.vec import FloatArray

UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class CameraPose:
    """A pinhole camera at `position_m` (world), looking along `yaw_deg` (from north, clockwise seen from above),
    `pitch_deg` below the horizontal, rolled by `roll_deg` about its optical axis."""

    image_size: tuple[int, int] = (1920, 1080)
    focal_px: float = 1400.0
    position_m: tuple[float, float, float] = (0.0, 0.0, 6.0)
    yaw_deg: float = 0.0
    pitch_deg: float = 25.0
    roll_deg: float = 1.0

    @property
    def principal_point(self) -> tuple[float, float]:
        return self.image_size[0] / 2.0, self.image_size[1] / 2.0

    @property
    def K(self) -> FloatArray:  # noqa: N802 - the conventional name
        cx, cy = self.principal_point
        return np.array([[self.focal_px, 0.0, cx], [0.0, self.focal_px, cy], [0.0, 0.0, 1.0]])

    @property
    def rotation(self) -> FloatArray:
        """World -> camera rotation: its rows are the camera's right, down and forward axes in the world."""
        yaw, pitch, roll = np.radians((self.yaw_deg, self.pitch_deg, self.roll_deg))
        forward = np.array([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), -np.sin(pitch)])
        right = np.array([np.cos(yaw), -np.sin(yaw), 0.0])
        down = np.cross(forward, right)
        # Roll turns right and down about the forward axis (the sense of bench.simulate.camera_normal).
        right, down = np.cos(roll) * right - np.sin(roll) * down, np.sin(roll) * right + np.cos(roll) * down
        return np.stack((right, down, forward))

    @property
    def normal(self) -> FloatArray:
        """The ground's up normal in the camera frame."""
        return self.rotation @ UP

    @property
    def rho_m(self) -> float:
        return float(self.position_m[2])

    def to_camera(self, points_world_m: FloatArray) -> FloatArray:
        return (np.asarray(points_world_m, dtype=float) - np.asarray(self.position_m)) @ self.rotation.T

    def project(self, points_world_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(pixels, depth in metres) of world points."""
        camera = self.to_camera(points_world_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = (camera @ self.K.T)[..., :2] / camera[..., 2:3]
        return pixels, camera[..., 2]

    def panned(self, degrees: float) -> CameraPose:
        """Turned about the world vertical through its centre (a pure pan)."""
        return replace(self, yaw_deg=self.yaw_deg + degrees)

    def tilted(self, degrees: float) -> CameraPose:
        """Pitched further down by `degrees` (negative: up)."""
        return replace(self, pitch_deg=self.pitch_deg + degrees)

    def rolled(self, degrees: float) -> CameraPose:
        return replace(self, roll_deg=self.roll_deg + degrees)

    def zoomed(self, factor: float) -> CameraPose:
        return replace(self, focal_px=self.focal_px * factor)

    def ground_point_at(self, pixel: tuple[float, float]) -> FloatArray:
        """The world ground point seen at `pixel` (which must lie below the horizon)."""
        ray_world = self.rotation.T @ (np.linalg.inv(self.K) @ np.array([pixel[0], pixel[1], 1.0]))
        if ray_world[2] >= 0:
            raise ValueError(f"pixel {pixel} lies on or above the horizon")
        return np.asarray(self.position_m) + ray_world * (-self.position_m[2] / ray_world[2])


@dataclass(frozen=True)
class CrowdConfig:
    """Who walks in the world, and how a pose model reports them."""

    people: int = 40
    """Everyone in the world (those in view are fewer: see `region_m`)."""
    region_m: tuple[float, float, float, float] = (-45.0, 45.0, 2.0, 60.0)
    """Where people walk: (x_min, x_max, y_min, y_max) on the ground, metres."""
    height_m: float = 1.32
    height_std_m: float = 0.07
    lean_std_deg: float = 2.0
    """Each person's persistent lean (and pose-model bias) from the vertical."""
    sitting_fraction: float = 0.025
    child_fraction: float = 0.025
    noise_px: float = 1.5
    gross_error_fraction: float = 0.01
    """Share of keypoint centres misplaced with 8x the noise."""
    speed_m_s: tuple[float, float] = (0.8, 1.6)
    turn_probability: float = 0.02


@dataclass
class Crowd:
    """People walking in the world; `step` moves them, `seen_by` is what a camera reports of them."""

    config: CrowdConfig
    rng: np.random.Generator
    positions_m: FloatArray = field(init=False)
    heights_m: FloatArray = field(init=False)
    leans_m: FloatArray = field(init=False)
    headings: FloatArray = field(init=False)
    speeds_m_s: FloatArray = field(init=False)
    kinds: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        c, rng, n = self.config, self.rng, self.config.people
        x0, x1, y0, y1 = c.region_m
        self.positions_m = np.stack((rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)), -1)
        self.heights_m = rng.normal(c.height_m, c.height_std_m, n)
        self.kinds = np.full(n, "adult", dtype=object)
        draw = rng.random(n)
        self.kinds[draw < c.sitting_fraction] = "sitting"
        children = (draw >= c.sitting_fraction) & (draw < c.sitting_fraction + c.child_fraction)
        self.kinds[children] = "child"
        self.heights_m[children] = rng.uniform(0.6, 0.95, int(children.sum()))
        sitting = self.kinds == "sitting"
        self.heights_m[sitting] *= rng.uniform(0.55, 0.7, int(sitting.sum()))
        lean = np.radians(rng.normal(0.0, c.lean_std_deg, n))
        direction = rng.uniform(0, 2 * np.pi, n)
        self.leans_m = (self.heights_m * np.tan(lean))[:, None] * np.stack((np.cos(direction), np.sin(direction)), -1)
        self.headings = rng.uniform(0, 2 * np.pi, n)
        self.speeds_m_s = np.where(sitting, 0.0, rng.uniform(*c.speed_m_s, n))

    def add_group(self, count: int, centre_m: tuple[float, float], heights_m: tuple[float, float]) -> np.ndarray:
        """A tight group (a school class) walking together from `centre_m`; returns their indices."""
        rng = self.rng
        offsets = rng.normal(0.0, 1.2, (count, 2))
        heading = rng.uniform(0, 2 * np.pi)
        start = len(self.heights_m)
        self.positions_m = np.vstack((self.positions_m, np.asarray(centre_m) + offsets))
        heights = rng.uniform(*heights_m, count)
        self.heights_m = np.concatenate((self.heights_m, heights))
        self.leans_m = np.vstack((self.leans_m, np.zeros((count, 2))))
        self.headings = np.concatenate((self.headings, np.full(count, heading)))
        self.speeds_m_s = np.concatenate((self.speeds_m_s, np.full(count, 1.0)))
        self.kinds = np.concatenate((self.kinds, np.full(count, "group", dtype=object)))
        return np.arange(start, start + count)

    def remove(self, indices: np.ndarray) -> None:
        keep = np.ones(len(self.heights_m), bool)
        keep[indices] = False
        for name in ("positions_m", "heights_m", "leans_m", "headings", "speeds_m_s", "kinds"):
            setattr(self, name, getattr(self, name)[keep])

    def step(self, dt_s: float) -> None:
        c, rng = self.config, self.rng
        n = len(self.headings)
        turning = rng.random(n) < c.turn_probability
        self.headings[turning] += rng.normal(0.0, 1.0, int(turning.sum()))
        move = (self.speeds_m_s * dt_s)[:, None] * np.stack((np.sin(self.headings), np.cos(self.headings)), -1)
        moved = self.positions_m + move
        x0, x1, y0, y1 = c.region_m
        outside = (moved[:, 0] < x0) | (moved[:, 0] > x1) | (moved[:, 1] < y0) | (moved[:, 1] > y1)
        self.headings[outside] += np.pi
        self.positions_m = np.where(outside[:, None], self.positions_m, moved)

    def seen_by(self, camera: CameraPose) -> tuple[FloatArray, FloatArray, np.ndarray]:
        """(tops_px, bottoms_px, indices) of the people whose shoulder and ankle centres are both in the image,
        with the pose model's noise; tops are shoulder centres, bottoms ankle centres."""
        c, rng = self.config, self.rng
        n = len(self.heights_m)
        bottoms_w = np.column_stack((self.positions_m, np.zeros(n)))
        tops_w = bottoms_w + np.column_stack((self.leans_m, self.heights_m))
        bottoms, depth_b = camera.project(bottoms_w)
        tops, depth_t = camera.project(tops_w)
        width, height = camera.image_size
        inside = (depth_b > 0.5) & (depth_t > 0.5)
        for points in (bottoms, tops):
            inside &= (points[:, 0] >= 0) & (points[:, 0] <= width) & (points[:, 1] >= 0) & (points[:, 1] <= height)
        index = np.flatnonzero(inside)
        tops, bottoms = tops[index], bottoms[index]
        for points in (tops, bottoms):
            scale = np.where(rng.random(len(index)) < c.gross_error_fraction, 8.0, 1.0) * c.noise_px
            points += rng.normal(0.0, 1.0, points.shape) * scale[:, None]
        return tops, bottoms, index


def street(seed: int, config: CrowdConfig | None = None) -> Crowd:
    """A crowd with the defaults: about 18 people in view of the default camera."""
    return Crowd(config or CrowdConfig(), np.random.default_rng(seed))
