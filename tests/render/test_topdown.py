"""The map from above: known metres land at known pixels, close pairs in red, the camera and its view."""

from __future__ import annotations

import numpy as np
import pytest

from service.frames.schemas import PairDistance
from service.render.overlay import PersonMark
from service.render.style import GREEN, RED, WHITE
from service.render.topdown import BACKGROUND, TopDownView, fit_view, nice_step, render_topdown
from tests.render.scenes import calibration_of, tilted_scene

# 801 x 801 pixels, 1 cm per pixel, centred on (0, 3) m: (u, v) -> (400 + 100 u, 400 - 100 (v - 3)).
VIEW = TopDownView(801, 801, (0.0, 3.0), 0.01)


def _is(color: np.ndarray, expected: tuple[int, int, int], tol: int = 40) -> bool:
    return bool(np.all(np.abs(color.astype(int) - np.array(expected)) <= tol))


def test_view_maps_metres_to_pixels():
    np.testing.assert_allclose(
        VIEW.to_pixels([[0.0, 3.0], [2.0, 5.0], [-1.5, 0.5]]), [[400, 400], [600, 200], [250, 650]]
    )
    np.testing.assert_allclose(VIEW.to_ground(VIEW.to_pixels([[1.234, -5.678]])), [[1.234, -5.678]], atol=1e-12)
    assert VIEW.extent_m == pytest.approx((-4.005, 4.005, -1.005, 7.005))


def test_people_land_at_their_pixels_and_close_pairs_are_red():
    people = [PersonMark(0, (2.0, 5.0)), PersonMark(1, (2.0, 4.0)), PersonMark(2, (-1.5, 0.5)), PersonMark(3, None)]
    pairs = [
        PairDistance(i=0, j=1, distance_m=1.0, distance_std_m=None),
        PairDistance(i=0, j=2, distance_m=5.7, distance_std_m=None),
        PairDistance(i=1, j=2, distance_m=4.9, distance_std_m=None),
        PairDistance(i=0, j=3, distance_m=None, distance_std_m=None),
    ]
    out = render_topdown(people, pairs, 1.8288, view=VIEW, threshold_circles=True)
    assert out.shape == (801, 801, 3)
    assert _is(out[200, 600], RED) and _is(out[300, 600], RED)  # people 0 and 1: (2, 5) and (2, 4) m
    assert _is(out[650, 250], GREEN)  # person 2 at (-1.5, 0.5) m
    # The pair line between 0 and 1 (x = 600, y 200..300) is red away from the label (above) and the dots.
    assert _is(out[280, 600], RED, tol=60) and _is(out[250, 600], RED, tol=60)
    # Threshold circle of person 2: radius 0.9144 m = 91.44 px to the right of it.
    ring = out[650, 250 + 89 : 250 + 95]
    assert any(_is(c, GREEN, tol=70) for c in ring)
    assert _is(out[650, 250 + 60], BACKGROUND, tol=12)  # inside the circle: background (or grid)


def test_camera_and_its_view_are_drawn():
    scene = tilted_scene(3)
    cal = calibration_of(scene)
    people = [PersonMark(0, (0.0, 6.0)), PersonMark(1, (1.0, 9.0))]
    out = render_topdown(people, [], 1.8288, size_px=(600, 500), calibration=cal)
    assert out.shape == (500, 600, 3)
    view = fit_view(np.array([[0.0, 6.0], [1.0, 9.0], [0.0, 0.0]]), (600, 500))
    cx, cy = np.rint(view.to_pixels([0.0, 0.0])).astype(int)
    assert _is(out[cy, cx], WHITE, tol=10)  # the camera's marker at its foot
    # The ground at 6 m ahead is inside the camera's view (tinted), the ground right behind the camera is not.
    ahead = np.rint(view.to_pixels([-0.5, 6.5])).astype(int)
    behind = np.rint(view.to_pixels([-0.5, -0.5])).astype(int)
    assert not _is(out[ahead[1], ahead[0]], BACKGROUND, tol=8)
    assert _is(out[behind[1], behind[0]], BACKGROUND, tol=8)


def test_fit_view_shows_every_point_with_equal_aspect():
    points = np.array([[-3.0, 2.0], [10.0, 30.0], [np.nan, 1.0]])
    view = fit_view(points, (400, 300), margin_m=1.0)
    px = view.to_pixels(points[:2])
    assert np.all(px >= 0) and np.all(px[:, 0] <= 399) and np.all(px[:, 1] <= 299)
    assert view.metres_per_px == pytest.approx(30.0 / 300)  # the tall side decides: 28 m + 2 m margin


@pytest.mark.parametrize("size", [1, (2, 1), (640, 480), (1920, 1080), (480, 800)])
def test_odd_sizes_do_not_crash(size):
    out = render_topdown(
        [PersonMark(0, (0.0, 1.0))], [], 1.8288, size_px=size, calibration=calibration_of(tilted_scene(3))
    )
    w, h = (size, size) if isinstance(size, int) else size
    assert out.shape == (h, w, 3)
    assert render_topdown([], [], 1.8288, size_px=size).shape == (h, w, 3)


def test_nice_steps():
    assert [nice_step(x) for x in (0.7, 1.0, 3.0, 7.5, 19.0, 20.0)] == [0.5, 1.0, 2.0, 5.0, 10.0, 20.0]
