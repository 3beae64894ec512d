"""Division-model distortion: exact on division-model scenes, the paper's pencil corrected, sane under noise."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.simulate import Scene, SceneConfig, draw_scene
from service.geometry import CalibrationError, CalibrationProblem, SolveOptions, calibrate, measure
from service.geometry.camera import ImageFrame, distort, undistort
from service.geometry.distortion import (
    collinearity_roots,
    estimate_division_k,
    paper_pencil,
    paper_roots,
    sampson_cost,
)
from service.geometry.vec import FloatArray
from tests.support.geometry import angle_deg

HEIGHT_M = 1.7
DIVISION_KS = [-0.1, -0.05, 0.05]


def division_scene(
    seed: int, k: float, noise_px: float = 0.0, **overrides: object
) -> tuple[Scene, ImageFrame, FloatArray, FloatArray]:
    """A pinhole scene whose normalised points are then distorted with the division model, plus pixel noise."""
    rng = np.random.default_rng(seed)
    config = SceneConfig.paper(noise_px=0.0, distortion_k=(0.0, 0.0), **overrides)
    s = draw_scene(config, rng)
    frame = ImageFrame.from_size(s.image_size)
    tops = distort(frame.normalise(s.tops_px), k) + rng.normal(0.0, noise_px / frame.scale_px, s.tops_px.shape)
    bottoms = distort(frame.normalise(s.bottoms_px), k) + rng.normal(0.0, noise_px / frame.scale_px, s.tops_px.shape)
    return s, frame, tops, bottoms


@given(
    st.floats(-0.8, 0.8),
    st.lists(st.tuples(st.floats(-1.5, 1.5), st.floats(-1.0, 1.0)), min_size=1, max_size=20),
)
@settings(max_examples=200, deadline=None)
def test_distort_inverts_undistort_on_the_monotone_range(k_r2: float, points: list[tuple[float, float]]) -> None:
    p = np.array(points)
    r2_max = max(float(np.max(np.sum(p * p, 1))), 1e-12)
    # As distorted points the model is monotone for |k| r^2 < 1; as undistorted ones they
    # have a preimage for 4 k r^2 <= 1.
    k = k_r2 / r2_max
    np.testing.assert_allclose(distort(undistort(p, k), k), p, rtol=0, atol=1e-12)
    k = k_r2 / (4.0 * r2_max)
    np.testing.assert_allclose(undistort(distort(p, k), k), p, rtol=0, atol=1e-12)


def test_zero_k_is_the_identity_and_invalid_points_are_nan() -> None:
    p = np.array([[0.0, 0.0], [0.3, -1.2], [1.5, 0.9]])
    np.testing.assert_array_equal(distort(p, 0.0), p)
    np.testing.assert_array_equal(undistort(p, 0.0), p)
    # k > 0: undistorted radius beyond 1 / (2 sqrt(k)) = 1 has no distorted preimage.
    assert np.isnan(distort(np.array([[1.2, 0.0]]), 0.25)).all()
    # k < 0: 1 + k r^2 <= 0 maps the point through infinity.
    assert np.isnan(undistort(np.array([[2.0, 0.0]]), -0.25)).all()
    assert distort(np.zeros((4, 3, 2)), 0.1).shape == (4, 3, 2)


@pytest.mark.parametrize("k", DIVISION_KS)
def test_corrected_paper_pencil_has_the_true_k_and_the_printed_one_does_not(k: float) -> None:
    """As printed, the last block row of A' has +x~'_B,N; the true (k, X') then no longer solves (A' + k C) X' = 0."""
    _, _, tops, bottoms = division_scene(1, k)
    a, c = paper_pencil(tops, bottoms, HEIGHT_M)
    assert np.linalg.svd(a + k * c, compute_uv=False)[-1] < 1e-13
    assert np.min(np.abs(paper_roots(tops, bottoms, HEIGHT_M) - k)) < 1e-9
    a_printed, c_printed = paper_pencil(tops, bottoms, HEIGHT_M, printed=True)
    assert np.linalg.svd(a_printed + k * c_printed, compute_uv=False)[-1] > 1e-4
    assert np.min(np.abs(paper_roots(tops, bottoms, HEIGHT_M, printed=True) - k)) > 1e-5
    assert np.min(np.abs(collinearity_roots(tops, bottoms) - k)) < 1e-12


@pytest.mark.parametrize("k", DIVISION_KS)
@pytest.mark.parametrize("equal_focal", [False, True])
def test_noise_free_division_scenes_are_recovered_exactly(k: float, equal_focal: bool) -> None:
    for seed in range(5):
        s, frame, tops, bottoms = division_scene(seed, k, square_pixels=equal_focal)
        cal = calibrate(
            frame.to_pixels(tops),
            frame.to_pixels(bottoms),
            CalibrationProblem(s.image_size, HEIGHT_M, equal_focal=equal_focal),
            SolveOptions(robust=False, refine=False, distortion=True),
        )
        assert cal.distortion_k == pytest.approx(k, abs=1e-8)
        assert cal.fx == pytest.approx(s.fx, rel=1e-7)
        assert cal.fy == pytest.approx(s.fy, rel=1e-7)
        assert angle_deg(cal.normal, s.normal) < 1e-6
        assert cal.rho == pytest.approx(s.rho, rel=1e-7)
        # Placement undoes the distortion too.
        np.testing.assert_allclose(
            measure(cal, frame.to_pixels(tops), frame.to_pixels(bottoms)).points_bottom,
            s.points_bottom,
            rtol=0,
            atol=1e-7 * s.rho,
        )


def test_undistorted_scene_gives_zero_k() -> None:
    for seed in range(5):
        _, _, tops, bottoms = division_scene(seed, 0.0)
        estimate = estimate_division_k(tops, bottoms, HEIGHT_M)
        assert abs(estimate.k) < 1e-8
        assert 0.0 in estimate.candidates_k


def test_three_people_determine_k() -> None:
    _, _, tops, bottoms = division_scene(4, -0.08, n_people=3)
    assert estimate_division_k(tops, bottoms, HEIGHT_M).k == pytest.approx(-0.08, abs=1e-8)


def test_large_crowds_skip_the_cubic_paper_problem() -> None:
    _, _, tops, bottoms = division_scene(2, 0.05, n_people=400, max_range_m=60.0)
    assert estimate_division_k(tops, bottoms, HEIGHT_M).k == pytest.approx(0.05, abs=1e-8)


def test_sampson_cost_is_zero_only_at_the_true_k() -> None:
    _, _, tops, bottoms = division_scene(3, -0.05)
    cost = sampson_cost(tops, bottoms, np.array([-0.1, -0.05, 0.0]))[0]
    assert cost[1] < 1e-25
    assert cost[0] > 1e-8 and cost[2] > 1e-8


def test_degenerate_inputs_raise() -> None:
    _, _, tops, bottoms = division_scene(5, -0.05)
    with pytest.raises(CalibrationError, match="at least 3"):
        estimate_division_k(tops[:2], bottoms[:2], HEIGHT_M)
    with pytest.raises(CalibrationError, match="zero-length"):
        estimate_division_k(np.vstack((tops[:3], bottoms[3:4])), bottoms[:4], HEIGHT_M)
    on_a_line = np.stack((np.linspace(-1.0, 1.0, 6), 0.2 * np.linspace(-1.0, 1.0, 6)), 1)
    with pytest.raises(CalibrationError, match="one image line"):
        estimate_division_k(on_a_line[::2], on_a_line[1::2], HEIGHT_M)
    # Camera looking straight down: every segment is radial, and radial lines are unchanged by any k.
    feet = np.random.default_rng(0).uniform(-1.0, 1.0, (8, 2))
    with pytest.raises(CalibrationError, match="not observable"):
        estimate_division_k(0.8 * feet, feet, HEIGHT_M)
    with pytest.raises(CalibrationError, match=r"\(N, 2\)"):
        estimate_division_k(tops[:, :1], bottoms[:, :1], HEIGHT_M)


def test_noisy_estimates_are_bounded_and_close() -> None:
    """0.5 px noise, 20 people: k stays finite and admissible, and is mostly within a few 1e-2 of the truth."""
    errors = []
    for k in (-0.1, 0.05):
        for seed in range(25):
            _, _, tops, bottoms = division_scene(100 + seed, k, noise_px=0.5)
            estimate = estimate_division_k(tops, bottoms, HEIGHT_M)
            assert np.isfinite(estimate.k)
            assert estimate.k_bounds[0] <= estimate.k <= estimate.k_bounds[1]
            errors.append(estimate.k - k)
    assert np.median(np.abs(errors)) < 0.015
    zero_chosen = [
        estimate_division_k(*division_scene(200 + seed, 0.0, noise_px=0.5)[2:], HEIGHT_M).k == 0.0 for seed in range(25)
    ]
    assert np.mean(zero_chosen) > 0.8


@pytest.mark.parametrize("k1", [-0.02, 0.05])
def test_correction_beats_plain_solve_on_the_opencv_polynomial_model(k1: float) -> None:
    """Noise-free data distorted with simulate's polynomial model (a different model from ours)."""
    rng = np.random.default_rng(17)
    config = SceneConfig.paper(distortion_k=(k1, 0.0), noise_px=0.0, square_pixels=True)
    plain, corrected = [], []
    while len(plain) < 20:
        s = draw_scene(config, rng)
        for errors, distortion in ((plain, False), (corrected, True)):
            try:
                cal = calibrate(
                    s.tops_px,
                    s.bottoms_px,
                    CalibrationProblem(s.image_size, HEIGHT_M),
                    SolveOptions(robust=False, refine=False, distortion=distortion),
                )
                errors.append((abs(cal.fx / s.fx - 1.0), angle_deg(cal.normal, s.normal)))
            except CalibrationError:
                errors.append((np.inf, np.inf))
    plain_median, corrected_median = np.median(plain, 0), np.median(corrected, 0)
    assert corrected_median[0] < 0.5 * plain_median[0]
    assert corrected_median[1] < 0.5 * plain_median[1]


@pytest.mark.parametrize("seed", [0, 1, 4])
def test_one_person_seen_in_many_frames_counts_once_in_the_lens_test(seed: int) -> None:
    # 20 people of a distortion-free camera (1.5 px noise, 1 deg lean), each seen in 12 frames with the same lean
    # and pose error plus 0.05 px: 240 observations, 20 individuals. Counted as 240 independent residuals, the
    # small cost drop a k buys is 12 times as "significant", and a spurious lens is chosen; counted once per
    # individual, it is not.
    scene = draw_scene(SceneConfig.surveillance(n_people=20, lean_deg=1.0), np.random.default_rng(seed))
    centre = np.array([scene.cx, scene.cy])
    rng = np.random.default_rng(100 + seed)
    tops = (np.repeat(scene.tops_px - centre, 12, 0) + rng.normal(0.0, 0.05, (240, 2))) / scene.fy
    bottoms = (np.repeat(scene.bottoms_px - centre, 12, 0) + rng.normal(0.0, 0.05, (240, 2))) / scene.fy
    individuals = np.repeat(np.arange(20), 12)
    assert estimate_division_k(tops, bottoms).k != 0.0
    assert estimate_division_k(tops, bottoms, individuals=individuals).k == 0.0
    with pytest.raises(CalibrationError, match="one label per person"):
        estimate_division_k(tops, bottoms, individuals=individuals[:-1])


def test_a_real_lens_is_still_found_when_individuals_vary_from_frame_to_frame() -> None:
    # 240 observations labelled as 20 individuals whose residuals are independent (noise drawn per frame): the
    # design effect stays near 1 and the lens is found as it is without labels.
    _, _, tops, bottoms = division_scene(3, -0.05, noise_px=1.0, n_people=240)
    individuals = np.repeat(np.arange(20), 12)
    plain = estimate_division_k(tops, bottoms).k
    labelled = estimate_division_k(tops, bottoms, individuals=individuals).k
    assert plain == pytest.approx(-0.05, abs=0.01) and labelled == plain


def test_the_undetected_lens_prior_widens_with_the_field_of_view() -> None:
    # Up to a 35 deg half-diagonal (tan^2 0.5: Town Centre's 22 deg, most street cameras) the 3 % corner shift;
    # wider, as a lens design's corner shift grows, tan^2 of the half-diagonal (service.geometry.problem).
    problem = CalibrationProblem((1920, 1080), 1.32)
    town_centre = 0.5 * np.hypot(1920, 1080) / 2696.4
    assert problem.lens_corner_spread(town_centre) == pytest.approx(0.03)
    assert problem.lens_corner_spread(np.sqrt(0.5)) == pytest.approx(0.03)
    assert problem.lens_corner_spread(1.0) == pytest.approx(0.06)
    assert problem.lens_corner_spread(np.sqrt(1.5)) == pytest.approx(0.09)
    assert CalibrationProblem((1920, 1080), 1.32, lens_corner_std=0.0).lens_corner_spread(2.0) == 0.0
