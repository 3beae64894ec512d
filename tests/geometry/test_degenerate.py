"""Inputs with no valid calibration raise CalibrationError with a reason: never a crash, never garbage."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import CalibrationError, CalibrationProblem, SolveOptions, calibrate
from tests.support.geometry import scene

SIZE = (1920, 1080)


@pytest.fixture(params=[False, True], ids=["batch", "robust"])
def robust(request: pytest.FixtureRequest) -> bool:
    return bool(request.param)


def test_fewer_people_than_the_minimum(robust: bool) -> None:
    s = scene(1, noise_px=0.0)
    with pytest.raises(CalibrationError, match="at least 2"):
        calibrate(s.tops_px[:1], s.bottoms_px[:1], CalibrationProblem(SIZE, 1.7), SolveOptions(robust=robust))
    with pytest.raises(CalibrationError, match="at least 3"):
        calibrate(
            s.tops_px[:2],
            s.bottoms_px[:2],
            CalibrationProblem(SIZE, 1.7, equal_focal=False),
            SolveOptions(robust=robust),
        )
    with pytest.raises(CalibrationError):
        calibrate(np.empty((0, 2)), np.empty((0, 2)), CalibrationProblem(SIZE, 1.7), SolveOptions(robust=robust))


def test_all_segments_on_one_image_line(robust: bool) -> None:
    xs = np.linspace(100, 1800, 10)
    tops = np.column_stack((xs, 0.3 * xs + 100))
    bottoms = np.column_stack((xs + 50, 0.3 * (xs + 50) + 100))
    with pytest.raises(CalibrationError):
        calibrate(tops, bottoms, CalibrationProblem(SIZE, 1.7), SolveOptions(robust=robust))


def test_zero_length_segments(robust: bool) -> None:
    pts = np.random.default_rng(0).uniform((0, 0), SIZE, (10, 2))
    with pytest.raises(CalibrationError, match="at least"):
        calibrate(pts, pts.copy(), CalibrationProblem(SIZE, 1.7), SolveOptions(robust=robust))


def test_zero_length_people_are_excluded_not_fatal() -> None:
    s = scene(2, noise_px=0.0, square_pixels=True)
    tops = s.tops_px.copy()
    tops[3] = s.bottoms_px[3]
    cal = calibrate(tops, s.bottoms_px, CalibrationProblem(SIZE, 1.7), SolveOptions(robust=False, refine=False))
    assert not cal.inliers[3]
    assert np.all(np.isnan(cal.points_bottom[3]))
    assert cal.fx == pytest.approx(s.fx, rel=1e-8)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_coordinates(bad: float) -> None:
    s = scene(3, noise_px=0.5)
    bottoms = s.bottoms_px.copy()
    bottoms[4, 1] = bad
    with pytest.raises(CalibrationError, match=r"bottoms\[4\] is not finite"):
        calibrate(s.tops_px, bottoms, CalibrationProblem(SIZE, 1.7))


def test_points_far_outside_the_image() -> None:
    s = scene(3, noise_px=0.5)
    tops = s.tops_px.copy()
    tops[2] = (1e7, -5e6)
    with pytest.raises(CalibrationError, match="far outside"):
        calibrate(tops, s.bottoms_px, CalibrationProblem(SIZE, 1.7))


@pytest.mark.parametrize(
    ("tops", "bottoms", "size", "height", "match"),
    [
        (np.zeros((3, 3)), np.zeros((3, 3)), SIZE, 1.7, "shape"),
        (np.zeros((3, 2)), np.zeros((4, 2)), SIZE, 1.7, "differ"),
        ([["a", "b"]], [["c", "d"]], SIZE, 1.7, "numbers"),
        (np.zeros((3, 2)), np.ones((3, 2)), (0, 1080), 1.7, "image_size"),
        (np.zeros((3, 2)), np.ones((3, 2)), SIZE, -1.0, "height"),
        (np.zeros((3, 2)), np.ones((3, 2)), SIZE, float("nan"), "height"),
    ],
)
def test_malformed_arguments(tops: object, bottoms: object, size: tuple[int, int], height: float, match: str) -> None:
    with pytest.raises(CalibrationError, match=match):
        calibrate(tops, bottoms, CalibrationProblem(size, height))  # type: ignore[arg-type]


def test_random_garbage_never_crashes_or_returns_nonsense() -> None:
    """Random segments either raise CalibrationError or give a finite, physically valid camera."""
    rng = np.random.default_rng(0)
    for _ in range(60):
        n = int(rng.integers(2, 30))
        bottoms = rng.uniform((0, 0), SIZE, (n, 2))
        tops = bottoms + rng.uniform((-200, -400), (200, 100), (n, 2))
        for robust in (False, True):
            try:
                cal = calibrate(
                    tops,
                    bottoms,
                    CalibrationProblem(SIZE, 1.7, equal_focal=bool(rng.integers(2))),
                    SolveOptions(robust=robust),
                )
            except CalibrationError:
                continue
            assert cal.fx > 0 and cal.fy > 0 and cal.rho > 0
            assert np.isfinite(cal.normal).all() and abs(np.linalg.norm(cal.normal) - 1) < 1e-9
            placed = cal.inliers
            assert np.all(np.isfinite(cal.points_bottom[placed]))
            assert np.all(cal.points_bottom[placed][:, 2] > 0)


def test_undetermined_focal_length_is_refused_not_reported() -> None:
    """Four noisy people (3 px) with varied heights: the solve lands on an f it cannot support."""
    s = scene(12, noise_px=3.0, n_people=4, square_pixels=True, height_std_m=0.1)
    with pytest.raises(CalibrationError, match="do not determine the focal length"):
        calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(SIZE, 1.7))
