"""The direct linear solver: exact on noise-free scenes, and the paper's printed errors corrected."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from bench.simulate import SceneConfig, draw_scene
from service.geometry import CalibrationError, SolveOptions
from service.geometry.camera import ImageFrame
from service.geometry.linear import focal_weights, scaled_depths, solve_linear, vanishing_point
from service.geometry.vec import homogeneous
from tests.support.geometry import angle_deg, scene, solve

RESOLUTIONS = [(640, 480), (1280, 720), (1920, 1080)]
FOVS = [45.0, 60.0, 90.0, 120.0]


@pytest.mark.parametrize(("size", "fov"), list(itertools.product(RESOLUTIONS, FOVS)))
@pytest.mark.parametrize("equal_focal", [False, True])
def test_noise_free_minimal_scenes_are_recovered_exactly(size: tuple[int, int], fov: float, equal_focal: bool) -> None:
    config = SceneConfig.paper(
        image_size=size,
        vfov_deg=(fov, fov),
        n_people=2 if equal_focal else 3,
        noise_px=0.0,
        square_pixels=equal_focal,
    )
    rng = np.random.default_rng(int(fov) + size[0])
    for _ in range(20):
        s = draw_scene(config, rng)
        # The linear solver alone: two or three people cannot also bound the nuisances a covariance would carry.
        cal = solve(s, SolveOptions(robust=False, refine=False, uncertainty=False), equal_focal=equal_focal)
        assert cal.fx == pytest.approx(s.fx, rel=1e-8)
        assert cal.fy == pytest.approx(s.fy, rel=1e-8)
        assert angle_deg(cal.normal, s.normal) < 1e-6
        assert cal.rho == pytest.approx(s.rho, rel=1e-8)
        for got, true in ((cal.points_bottom, s.points_bottom), (cal.points_top, s.points_top)):
            # The paper's metric: error relative to the point's distance, here < 1e-6 %.
            assert np.max(np.linalg.norm(got - true, axis=1) / np.linalg.norm(true, axis=1)) < 1e-8


@pytest.mark.parametrize("robust", [False, True])
def test_default_pipeline_is_exact_on_noise_free_crowds(robust: bool) -> None:
    s = scene(3, noise_px=0.0, n_people=40)
    cal = solve(s, SolveOptions(robust=robust), equal_focal=False)
    assert cal.refined
    assert cal.fx == pytest.approx(s.fx, rel=1e-7)
    assert cal.fy == pytest.approx(s.fy, rel=1e-7)
    assert angle_deg(cal.normal, s.normal) < 1e-6
    assert cal.rho == pytest.approx(s.rho, rel=1e-7)
    assert cal.inliers.all()


def test_centred_ground_rows_equal_all_pairs_least_squares() -> None:
    """The O(N) centred form of Eq. 3 has the same least-squares solution as the N(N-1)/2 pairs."""
    s = scene(11, noise_px=1.0, n_people=15)
    frame = ImageFrame.from_size(s.image_size)
    t, b = homogeneous(frame.normalise(s.tops_px)), homogeneous(frame.normalise(s.bottoms_px))
    v = vanishing_point(t, b)[None, :]
    _, lam_b = scaled_depths(t, b, v, 1.7)
    p = b * lam_b[:, None]
    i, j = np.triu_indices(len(p), 1)
    d = p[i] - p[j]
    rows = np.stack((v[0, 0] * d[:, 0], v[0, 1] * d[:, 1]), 1)
    expected = np.linalg.lstsq(rows, -v[0, 2] * d[:, 2], rcond=None)[0]
    np.testing.assert_allclose(focal_weights(b, lam_b, v, equal_focal=False), expected, rtol=1e-9)
    expected_eq = np.linalg.lstsq(rows.sum(1, keepdims=True), -v[0, 2] * d[:, 2], rcond=None)[0][0]
    np.testing.assert_allclose(focal_weights(b, lam_b, v, equal_focal=True), [expected_eq, expected_eq], rtol=1e-9)


def test_printed_formulas_are_wrong_and_corrections_right() -> None:
    """As printed, mu = v'Wv (no square root) and y = +v3 d3 do not reproduce an exact scene."""
    s = scene(5, noise_px=0.0, height_std_m=0.0)
    frame = ImageFrame.from_size(s.image_size)
    t, b = homogeneous(frame.normalise(s.tops_px)), homogeneous(frame.normalise(s.bottoms_px))
    v = vanishing_point(t, b)[None, :]
    _, lam_b = scaled_depths(t, b, v, 1.7)
    w = focal_weights(b, lam_b, v, equal_focal=False)
    np.testing.assert_allclose(w, [(frame.scale_px / s.fx) ** 2, (frame.scale_px / s.fy) ** 2], rtol=1e-9)
    # Printed sign of y: the least-squares solution flips to -W, i.e. no real focal length.
    d = b * lam_b[:, None]
    d = d - d.mean(0)
    rows = np.stack((v[0, 0] * d[:, 0], v[0, 1] * d[:, 1]), 1)
    printed = np.linalg.lstsq(rows, +v[0, 2] * d[:, 2], rcond=None)[0]
    np.testing.assert_allclose(printed, -w, rtol=1e-9)
    # Printed scale: without the square root K^-1 v / mu is not a unit normal.
    k_inv_v = v[0] * np.array([np.sqrt(w[0]), np.sqrt(w[1]), 1.0])
    vwv = float(v[0] @ (v[0] * np.array([w[0], w[1], 1.0])))
    assert np.linalg.norm(k_inv_v / np.sqrt(vwv)) == pytest.approx(1.0, abs=1e-12)
    assert abs(np.linalg.norm(k_inv_v / vwv) - 1.0) > 1e-3


def test_known_focal_length_solves_only_the_ground_plane() -> None:
    s = scene(9, noise_px=0.0, square_pixels=True)
    cal = solve(s, SolveOptions(robust=False, refine=False), focal_px=s.fx)
    assert cal.fx == s.fx
    assert cal.rho == pytest.approx(s.rho, rel=1e-9)
    assert angle_deg(cal.normal, s.normal) < 1e-7


def test_normal_points_up_and_people_are_in_front() -> None:
    s = scene(2, noise_px=0.5)
    cal = solve(s, equal_focal=False)
    assert cal.normal @ s.normal > 0.99
    assert np.all(cal.points_bottom[cal.inliers][:, 2] > 0)
    assert np.linalg.norm(cal.normal) == pytest.approx(1.0)


def test_fx_is_unobservable_without_roll() -> None:
    """A level camera (zero roll, centred principal point) cannot separate fx from fy."""
    s = scene(4, noise_px=0.0, roll_deg=(0.0, 0.0))
    frame = ImageFrame.from_size(s.image_size)
    with pytest.raises(CalibrationError, match="fx and fy"):
        solve_linear(frame.normalise(s.tops_px), frame.normalise(s.bottoms_px), 1.7, equal_focal=False)
    cal = solve(s, SolveOptions(robust=False, refine=False), equal_focal=True)
    assert np.isfinite(cal.fx)
