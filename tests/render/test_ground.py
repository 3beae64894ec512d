"""The drawing frame: same ground coordinates as the stored results, exact projections, the visible ground."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bench.simulate import project
from service.render.ground import GroundFrame, clip_line_to_polygon, ground_axes
from tests.render.scenes import calibration_of, people_of, result_of, tilted_scene


@pytest.fixture(scope="module")
def scene():
    return tilted_scene(3)


@pytest.fixture(scope="module")
def frame(scene) -> GroundFrame:
    return GroundFrame.from_calibration(calibration_of(scene))


def test_ground_coordinates_are_the_stored_ground_m(scene, frame):
    result = result_of(scene, people_of(scene, hide_ankles=(2,)), 1.8288)
    for person in result.people:
        assert person.point_m is not None and person.ground_m is not None
        np.testing.assert_allclose(frame.camera_to_ground(np.array(person.point_m)), person.ground_m, atol=1e-9)
    # And the people land where the simulator put them (exact scene, true camera).
    ground = frame.camera_to_ground(scene.points_bottom)
    stored = np.array([p.ground_m for p in result.people])
    np.testing.assert_allclose(stored, ground, atol=1e-6)


def test_axes_are_orthonormal_right_handed_and_on_the_plane(frame):
    right, forward = frame.axes
    n = frame.normal
    assert abs(right @ forward) < 1e-12 and abs(right @ n) < 1e-12 and abs(forward @ n) < 1e-12
    np.testing.assert_allclose(np.cross(right, forward), n, atol=1e-12)
    assert forward[2] > 0.9  # forward is the optical axis projected: mostly +z for a 15-20 degree pitch
    # A camera looking straight down still gets a frame (forward = image up).
    r, f = ground_axes([0.0, 0.0, -1.0])
    np.testing.assert_allclose(f, [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(r, [1.0, 0.0, 0.0], atol=1e-12)  # image right, as for any camera


def test_projection_matches_the_simulator_and_inverts(scene, frame):
    uv = np.random.default_rng(0).uniform([-5, 2], [5, 20], (50, 2))
    px = frame.ground_to_pixels(uv)
    expected = project(frame.ground_to_camera(uv), scene.fx, scene.fy, scene.cx, scene.cy)
    np.testing.assert_allclose(px, expected, atol=1e-9)
    np.testing.assert_allclose(frame.pixels_to_ground(px), uv, atol=1e-6)
    x = frame.pixels_to_camera(px)
    np.testing.assert_allclose(x @ frame.normal + frame.rho, 0.0, atol=1e-9)


def test_projection_with_distortion_inverts(frame):
    bent = replace(frame, distortion_k=-0.08)
    uv = np.random.default_rng(1).uniform([-4, 3], [4, 15], (50, 2))
    px = bent.ground_to_pixels(uv)
    assert np.max(np.abs(px - frame.ground_to_pixels(uv))) > 1.0  # distortion does move points
    np.testing.assert_allclose(bent.pixels_to_ground(px), uv, atol=1e-6)


def test_ground_behind_the_camera_and_sky_do_not_project(frame):
    assert np.all(np.isnan(frame.ground_to_pixels(np.array([[0.0, -5.0]]))))
    sky = np.array([[frame.width_px / 2, 0.0]])
    assert frame.below_horizon_px(sky)[0] < 0
    assert np.all(np.isnan(frame.pixels_to_ground(sky)))


def test_horizon_is_where_far_ground_goes(frame):
    far = frame.ground_to_pixels(np.array([[-1e7, 1e7], [0.0, 1e7], [1e7, 1e7]]))
    np.testing.assert_allclose(far[:, 1], frame.horizon_y(far[:, 0]), atol=1e-3)
    assert 0 < frame.horizon_y(np.array([frame.width_px / 2]))[0] < frame.height_px / 2


def test_visible_polygon_is_inside_the_image_and_below_the_margin(frame):
    poly = frame.visible_polygon(horizon_margin_px=20.0, max_range_m=30.0)
    assert len(poly) >= 4
    px = frame.ground_to_pixels(poly)
    assert np.all(px >= -1e-6) and np.all(px <= np.array([frame.width_px, frame.height_px]) + 1e-6)
    assert np.all(frame.below_horizon_px(px) >= 20.0 - 1e-6)
    assert np.all(np.hypot(poly[:, 0], poly[:, 1]) <= 30.0 * 1.0013)
    # The bottom corners of the image are ground and are vertices of the polygon.
    corners = frame.pixels_to_ground(np.array([[0.0, frame.height_px], [frame.width_px, frame.height_px]]))
    for c in corners:
        assert np.min(np.hypot(*(poly - c).T)) < 1e-9


def test_clip_line_to_a_non_convex_polygon():
    # A "U" shape: the line y = 1 crosses both arms.
    u = np.array([[0, 0], [3, 0], [3, 2], [2, 2], [2, 0.5], [1, 0.5], [1, 2], [0, 2]], dtype=float)
    spans = clip_line_to_polygon(np.array([-1.0, 1.0]), np.array([1.0, 0.0]), u)
    np.testing.assert_allclose(spans, [(1.0, 2.0), (3.0, 4.0)], atol=1e-12)
    assert clip_line_to_polygon(np.array([0.0, 5.0]), np.array([1.0, 0.0]), u) == []
