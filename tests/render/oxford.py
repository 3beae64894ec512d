"""The Oxford Town Centre camera's published calibration as a posemetry Calibration (for sample pictures).

The `.ci` file gives K, a rotation quaternion (x, y, z, w) and a translation with X_cam = R X_world + T, and
OpenCV distortion (k1, k2, p1, p2). The world plane z = 0 is the ground: in the camera frame its normal is
+-R e_z and, from (R e_z) . (X_cam - T) = 0, the plane is N . X + rho = 0 with rho = -N . T; the sign is
chosen so that N points up (rho > 0, camera above the ground). posemetry's one-parameter division model cannot
represent this lens (k1 < 0 with a large k2 > 0), so frames are undistorted with OpenCV first and drawn on
with distortion_k = 0.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from service.frames.schemas import PairDistance
from service.geometry.calibration import Calibration
from service.render.ground import GroundFrame
from service.render.overlay import PersonMark


def read_ci(path: Path) -> dict[str, float]:
    values = {}
    for raw in path.read_text().splitlines():
        if "=" in raw:
            key, value = raw.split("=", 1)
            values[key.strip()] = float(value)
    return values


def rotation(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w)."""
    q = np.array([qx, qy, qz, qw]) / np.linalg.norm([qx, qy, qz, qw])
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def oxford_calibration(path: Path, image_size_px: tuple[int, int] = (1920, 1080)) -> Calibration:
    """The published camera (distortion left out: use `undistort_frame` on the pictures)."""
    ci = read_ci(path)
    r = rotation(ci["RotationX"], ci["RotationY"], ci["RotationZ"], ci["RotationW"])
    t = np.array([ci["TranslationX"], ci["TranslationY"], ci["TranslationZ"]])
    normal = r[:, 2].copy()
    rho = float(-normal @ t)
    if normal[1] > 0:
        normal, rho = -normal, -rho
    return Calibration(
        fx=ci["FocalLengthX"],
        fy=ci["FocalLengthY"],
        cx=ci["PrincipalPointX"],
        cy=ci["PrincipalPointY"],
        normal=normal,
        rho=rho,
        image_size=(float(image_size_px[0]), float(image_size_px[1])),
        height_m=1.35,
        points_bottom=np.zeros((0, 3)),
        points_top=np.zeros((0, 3)),
        heights=np.zeros(0),
        inliers=np.zeros(0, dtype=bool),
    )


def undistort_frame(frame: np.ndarray, path: Path) -> np.ndarray:
    """The frame with the published OpenCV distortion removed (same K)."""
    ci = read_ci(path)
    k = np.array(
        [[ci["FocalLengthX"], 0, ci["PrincipalPointX"]], [0, ci["FocalLengthY"], ci["PrincipalPointY"]], [0, 0, 1]]
    )
    dist = np.array([ci["DistortionK1"], ci["DistortionK2"], ci["DistortionP1"], ci["DistortionP2"]])
    return cv2.undistort(frame, k, dist)


def oxford_people(
    top_path: Path, cal: Calibration, frame_number: int = 0
) -> tuple[list[PersonMark], list[PairDistance]]:
    """The hand-labelled people of one frame: body box, foot = bottom centre of the box, placed on the ground.

    Ground truth boxes are in the distorted frame; foot points are undistorted here only to first order (the
    published lens bends the picture by a few pixels at most in the middle of the frame), good enough to look at.
    """
    frame = GroundFrame.from_calibration(cal)
    marks = []
    for raw in top_path.read_text().splitlines():
        v = raw.split(",")
        if len(v) < 12 or not v[1].strip().isdigit() or int(v[1]) != frame_number or v[3].strip() != "1":
            continue
        x0, y0, x1, y1 = (float(t) for t in v[8:12])
        foot = ((x0 + x1) / 2, y1)
        ground = frame.pixels_to_ground(np.array(foot))
        placed = bool(np.all(np.isfinite(ground)))
        marks.append(
            PersonMark(
                index=len(marks),
                ground_m=(float(ground[0]), float(ground[1])) if placed else None,
                foot_px=foot,
                box_px=(x0, y0, x1, y1),
            )
        )
    pairs = []
    for i, a in enumerate(marks):
        for b in marks[i + 1 :]:
            d = (
                None
                if a.ground_m is None or b.ground_m is None
                else float(np.hypot(*np.subtract(a.ground_m, b.ground_m)))
            )
            pairs.append(PairDistance(i=a.index, j=b.index, distance_m=d, distance_std_m=None))
    return marks, pairs
