"""The camera model: OpenCV's lens inverted exactly, projection and rays consistent, a given lens used exactly."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.simulate import SceneConfig, draw_scene
from service.geometry import CalibrationError, CalibrationProblem, OpenCVLens, SolveOptions, calibrate, measure
from service.geometry.camera import Camera
from tests.support.geometry import angle_deg, ideal

# Published and typical lenses: Oxford Town Centre's (k1 -0.60, k2 4.70), a wide-angle webcam, a mild one.
LENSES = [
    OpenCVLens(-0.60150605, 4.70203733, -0.00047452, -0.00782290),
    OpenCVLens(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
    OpenCVLens(-0.05, 0.01, 0.0, 0.0, 0.001),
]


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(LENSES), st.floats(-0.35, 0.35), st.floats(-0.3, 0.3))
def test_undistort_inverts_distort_inside_the_lens_range(lens: OpenCVLens, x: float, y: float) -> None:
    xy = np.array([[x, y]])
    np.testing.assert_allclose(lens.undistort(lens.distort(xy)), xy, atol=1e-10)


def test_coefficients_round_trip_and_are_checked() -> None:
    lens = OpenCVLens.from_coefficients([-0.1, 0.02, 0.001, -0.002])
    assert lens.coefficients == (-0.1, 0.02, 0.001, -0.002, 0.0)
    with pytest.raises(ValueError, match="4 or 5"):
        OpenCVLens.from_coefficients([0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="finite"):
        OpenCVLens.from_coefficients([0.1, np.nan, 0.0, 0.0])


# A camera has one lens model: no lens, the division model (k) or OpenCV's.
@pytest.mark.parametrize(("lens", "k"), [(None, 0.0), (None, -0.04), (LENSES[1], 0.0)])
def test_projection_and_rays_agree(lens: OpenCVLens | None, k: float) -> None:
    camera = Camera(900.0, 910.0, 950.0, 520.0, (1920, 1080), distortion_k=k, lens=lens)
    points = np.random.default_rng(0).uniform((-3.0, -2.0, 4.0), (3.0, 2.0, 12.0), (50, 3))
    pixels = camera.project(points)
    ray = camera.rays(pixels)
    np.testing.assert_allclose(ray, points / points[:, 2:], atol=1e-9)
    np.testing.assert_allclose(camera.distort_px(camera.undistort_px(pixels)), pixels, atol=1e-7)


def test_a_given_lens_is_taken_exactly_with_or_without_the_focal_length() -> None:
    """Noise-free people seen through a strong polynomial lens: given its coefficients, the camera is exact."""
    config = SceneConfig.surveillance(noise_px=0.0, height_std_m=0.0, n_people=60, distortion_k=(-0.15, 0.02))
    s = draw_scene(config, np.random.default_rng(4))
    lens = OpenCVLens(-0.15, 0.02)
    exact = {**ideal(s), "height_std_m": 1e-6}
    options = SolveOptions(distortion=False)
    plain = calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, 1.7, **exact), options)
    for focal in (s.fx, None):
        problem = CalibrationProblem(s.image_size, 1.7, lens=lens, focal_px=focal, **exact)
        cal = calibrate(s.tops_px, s.bottoms_px, problem, options)
        assert cal.lens == lens and cal.distortion_source == "given"
        assert cal.fx == pytest.approx(s.fx, rel=1e-4) and cal.rho == pytest.approx(s.rho, rel=1e-4)
        assert angle_deg(cal.normal, s.normal) < 0.01
        placed = measure(cal, s.tops_px, s.bottoms_px).points_bottom
        np.testing.assert_allclose(placed, s.points_bottom, atol=1e-3 * s.rho)
    # Without the lens the same people give a visibly wrong camera.
    assert abs(plain.fx / s.fx - 1) > 10 * abs(cal.fx / s.fx - 1)


def test_bad_camera_inputs_are_refused_when_the_problem_is_made() -> None:
    for bad, match in (
        ({"principal_point_px": (np.nan, 3.0)}, "principal_point_px"),
        ({"focal_px": (1000.0, -1.0)}, "focal_px"),
        ({"camera_height_m": -2.0}, "camera_height_m"),
        ({"camera_height_m": 5.0, "camera_height_std_m": 0.0}, "camera_height_std_m"),
        ({"principal_point_std": -0.1}, "principal_point_std"),
    ):
        with pytest.raises(CalibrationError, match=match):
            CalibrationProblem((1920, 1080), **bad)  # type: ignore[arg-type]
