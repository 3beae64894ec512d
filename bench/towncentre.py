"""Oxford Town Centre ground truth for benchmarks and tests: the published calibration and the annotated boxes.

Calibration file (`TownCentre-calibration-ci.txt`): focal lengths and principal point in pixels, a rotation
quaternion (x, y, z, w), a translation and Brown distortion K1, K2, P1, P2. Which convention the numbers follow is
not stated upstream, so it was determined from the data (see tests/pose/test_towncentre.py): of the four readings of
(R, T) and the three world axes, only `X_cam = R X_world + T` with world z vertical (up) puts every annotated foot
in front of the camera and every annotated head top a consistent ~1.75 m above its foot (spread ~5 cm in frame 0);
the camera then sits ~7.8 m above the street. The ground plane z_world = 0 in camera coordinates (x right, y
down, z forward) is N . X + rho = 0 with N = R e_z (pointing up) and rho = -N . T (the camera height, > 0).
"""

from __future__ import annotations

import csv
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.geometry import DEFAULT_HEIGHT_M, Calibration


@dataclass(frozen=True)
class TownCentreCalibration:
    """The published camera: intrinsics, world-to-camera pose and distortion."""

    fx: float
    fy: float
    cx: float
    cy: float
    rotation: np.ndarray
    """(3, 3) world-to-camera rotation R (X_cam = R X_world + T)."""
    translation: np.ndarray
    """(3,) T in metres."""
    distortion: tuple[float, float, float, float]
    """K1, K2, P1, P2 (Brown model on focal-normalised coordinates)."""

    @property
    def ground_normal(self) -> np.ndarray:
        """Unit normal of the street in camera coordinates, pointing up (towards the sky, so its y is negative)."""
        return self.rotation[:, 2].copy()

    @property
    def ground_rho(self) -> float:
        """rho of N . X + rho = 0 for the street: the camera's height above it in metres."""
        return float(-self.ground_normal @ self.translation)

    def to_camera(self, world: np.ndarray) -> np.ndarray:
        return np.asarray(world, dtype=np.float64) @ self.rotation.T + self.translation

    def project(self, camera_points: np.ndarray, *, distort: bool = True) -> np.ndarray:
        """(N, 3) camera-frame points to (N, 2) pixels, with the published lens distortion unless told otherwise."""
        pts = np.asarray(camera_points, dtype=np.float64)
        x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
        if distort:
            k1, k2, p1, p2 = self.distortion
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            x, y = (
                x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
            )
        return np.c_[self.fx * x + self.cx, self.fy * y + self.cy]

    def undistort(self, pixels: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Pixels to focal-normalised undistorted (x, y), by fixed-point iteration (converges fast at r < 0.5)."""
        px = np.asarray(pixels, dtype=np.float64)
        xd, yd = (px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy
        k1, k2, p1, p2 = self.distortion
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial
            y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial
        return np.c_[x, y]

    def ground_points(self, pixels: np.ndarray, *, distort: bool = True) -> np.ndarray:
        """(N, 3) camera-frame points where the pixels' rays meet the street (NaN for rays that miss it)."""
        px = np.asarray(pixels, dtype=np.float64)
        if distort:
            xy = self.undistort(px)
        else:
            xy = np.c_[(px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy]
        rays = np.c_[xy, np.ones(len(xy))]
        depth = -self.ground_rho / (rays @ self.ground_normal)
        depth = np.where(depth > 0, depth, np.nan)
        return rays * depth[:, None]


def camera(
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    normal: np.ndarray,
    rho: float,
    image_size: tuple[float, float],
    height_m: float = DEFAULT_HEIGHT_M,
) -> Calibration:
    """A camera as the geometry's Calibration, without the per-person arrays of a solve (a known or stored camera)."""
    none = np.zeros((0, 3))
    return Calibration(
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        normal=np.asarray(normal, dtype=np.float64),
        rho=rho,
        image_size=(float(image_size[0]), float(image_size[1])),
        height_m=height_m,
        points_bottom=none,
        points_top=none,
        heights=np.zeros(0),
        inliers=np.zeros(0, dtype=bool),
    )


def as_calibration(town: TownCentreCalibration, height_m: float = DEFAULT_HEIGHT_M) -> Calibration:
    """The published camera as the geometry's Calibration (lens distortion dropped: it moves no pixel by more than
    ~2 % of a person's height), e.g. to guide the detector as a solved camera would."""
    return camera(town.fx, town.fy, town.cx, town.cy, town.ground_normal, town.ground_rho, (1920, 1080), height_m)


def load_calibration(path: Path) -> TownCentreCalibration:
    """Parse `Key = value` lines of the `.ci` calibration file."""
    values: dict[str, float] = {}
    for line in path.read_text().splitlines():
        if "=" in line:
            key, value = line.split("=", 1)
            values[key.strip()] = float(value)
    qx, qy, qz, qw = (values[f"Rotation{c}"] for c in "XYZW")
    norm = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
    rotation = np.array(
        [
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
            [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
            [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
        ]
    )
    return TownCentreCalibration(
        fx=values["FocalLengthX"],
        fy=values["FocalLengthY"],
        cx=values["PrincipalPointX"],
        cy=values["PrincipalPointY"],
        rotation=rotation,
        translation=np.array([values["TranslationX"], values["TranslationY"], values["TranslationZ"]]),
        distortion=(values["DistortionK1"], values["DistortionK2"], values["DistortionP1"], values["DistortionP2"]),
    )


@dataclass(frozen=True)
class Annotation:
    """One annotated person in one frame (pixels of the 1920x1080 frame)."""

    person: int
    head_xyxy: tuple[float, float, float, float] | None
    body_xyxy: tuple[float, float, float, float] | None


def load_annotations(path: Path, frames: set[int] | None = None) -> dict[int, list[Annotation]]:
    """frame number (0-based) -> annotations; rows with the wrong field count (the truncated last line) are skipped."""
    by_frame: dict[int, list[Annotation]] = defaultdict(list)
    with path.open(newline="") as handle:
        for row in csv.reader(handle):
            if len(row) != 12 or not row[0].strip().isdigit():
                continue
            person, frame, head_valid, body_valid = (int(v) for v in row[:4])
            if frames is not None and frame not in frames:
                continue
            head = tuple(float(v) for v in row[4:8]) if head_valid else None
            body = tuple(float(v) for v in row[8:12]) if body_valid else None
            by_frame[frame].append(Annotation(person, head, body))  # type: ignore[arg-type]
    return dict(by_frame)
