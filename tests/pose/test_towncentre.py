"""The Town Centre calibration helper: its ground plane must carry the annotated pedestrians consistently."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.towncentre import TownCentreCalibration, load_annotations, load_calibration

FRAMES = set(range(0, 126, 6))


@pytest.fixture(scope="module")
def calibration(town_dir: Path) -> TownCentreCalibration:
    return load_calibration(town_dir / "TownCentre-calibration-ci.txt")


@pytest.fixture(scope="module")
def feet_and_heads(town_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Bottom-centre of the body box and top-centre of the head box of people fully in view."""
    feet, heads = [], []
    for people in load_annotations(town_dir / "TownCentre-groundtruth.top", FRAMES).values():
        for person in people:
            if person.body_xyxy is None or person.head_xyxy is None or person.body_xyxy[3] > 1075:
                continue
            body, head = person.body_xyxy, person.head_xyxy
            feet.append(((body[0] + body[2]) / 2, body[3]))
            heads.append(((head[0] + head[2]) / 2, head[1]))
    return np.array(feet), np.array(heads)


def test_parsed_values(calibration: TownCentreCalibration) -> None:
    assert calibration.fx == pytest.approx(2696.3589, abs=1e-3) and calibration.cx == 959.5
    np.testing.assert_allclose(calibration.rotation @ calibration.rotation.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(calibration.rotation) == pytest.approx(1.0)


def test_ground_plane_is_below_camera_and_normal_points_up(calibration: TownCentreCalibration) -> None:
    normal = calibration.ground_normal
    assert np.linalg.norm(normal) == pytest.approx(1.0)
    assert normal[1] < -0.5  # up is image-up: negative y in x-right, y-down camera coordinates
    assert 5.0 < calibration.ground_rho < 12.0  # an upper-floor window: ~7.8 m
    # A world point on z = 0 satisfies N . X + rho = 0 in camera coordinates.
    on_ground = calibration.to_camera(np.array([[3.0, -2.0, 0.0], [10.0, 5.0, 0.0]]))
    np.testing.assert_allclose(on_ground @ normal + calibration.ground_rho, 0.0, atol=1e-9)


def test_feet_reproject_onto_the_ground_plane(calibration: TownCentreCalibration) -> None:
    """Feet back-projected onto the plane and projected again land on the same pixels (plane + distortion maps)."""
    pixels = np.array([[300.0, 1000.0], [960.0, 540.0], [1700.0, 300.0], [50.0, 200.0]])
    ground = calibration.ground_points(pixels)
    assert np.all(np.isfinite(ground))
    np.testing.assert_allclose(ground @ calibration.ground_normal + calibration.ground_rho, 0.0, atol=1e-9)
    np.testing.assert_allclose(calibration.project(ground), pixels, atol=1e-3)


def test_annotated_people_stand_a_consistent_height_on_the_plane(
    calibration: TownCentreCalibration, feet_and_heads: tuple[np.ndarray, np.ndarray]
) -> None:
    """Every annotated foot lies in front of the camera, and the head top straight above it is ~1.75 m up.

    This is what fixes the convention: with any other reading of (R, T) or another vertical axis, feet fall behind
    the camera or the implied heights scatter by metres.
    """
    feet, heads = feet_and_heads
    assert len(feet) > 150
    ground = calibration.ground_points(feet)
    assert np.all(np.isfinite(ground)) and np.all(ground[:, 2] > 0)
    heights = []
    normal = calibration.ground_normal
    candidates = np.linspace(0.5, 2.5, 401)
    for foot, head in zip(ground, heads, strict=True):
        tops = calibration.project(foot + candidates[:, None] * normal)
        heights.append(candidates[np.argmin(np.abs(tops[:, 1] - head[1]))])
        # The head top also sits where "straight up" leads, horizontally (to the annotation's precision).
        assert abs(tops[np.argmin(np.abs(tops[:, 1] - head[1])), 0] - head[0]) < 40
    heights_m = np.array(heights)
    assert 1.6 < np.median(heights_m) < 1.95
    assert np.percentile(np.abs(heights_m - np.median(heights_m)), 90) < 0.2
