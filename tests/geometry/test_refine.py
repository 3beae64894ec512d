"""The MAP fit's structure: one height per individual, consider parameters, no shrinking world, exact when exact."""

from __future__ import annotations

import numpy as np
import pytest

from bench.moving_camera import CameraPose
from bench.simulate import SceneConfig, draw_scene
from service.geometry import CalibrationProblem, calibrate
from service.geometry.model import Layout, Priors
from service.geometry.refine import _consider_covariance, _track_sums
from tests.support.geometry import angle_deg, ideal


def test_an_individual_seen_many_times_has_one_height_and_counts_once() -> None:
    s = draw_scene(SceneConfig.realistic(n_people=120), np.random.default_rng(3))
    problem = CalibrationProblem(s.image_size, 1.32)
    linked = calibrate(s.tops_px, s.bottoms_px, problem, tracks=s.tracks)
    alone = calibrate(s.tops_px, s.bottoms_px, problem)
    placed = linked.inliers
    for label in np.unique(s.tracks[placed]):
        heights = linked.heights[placed & (s.tracks == label)]
        assert np.ptp(heights) < 1e-9
    assert linked.individuals == len(np.unique(s.tracks[placed])) < alone.individuals
    # Thirty people seen four times are not 120 people: the linked solve is less sure of itself.
    assert linked.uncertainty is not None and alone.uncertainty is not None
    assert linked.uncertainty.rho_m > alone.uncertainty.rho_m


def test_the_scale_comes_from_the_mean_height_prior_unshrunk() -> None:
    """Heights spread 5 %, nothing else wrong: the camera height lands on the truth, not a shrunken world."""
    errors = []
    for seed in range(6):
        s = draw_scene(
            SceneConfig.surveillance(n_people=100, noise_px=0.5, height_std_m=0.085), np.random.default_rng(seed)
        )
        cal = calibrate(
            s.tops_px,
            s.bottoms_px,
            CalibrationProblem(s.image_size, float(np.mean(s.heights)), **{**ideal(s), "mean_height_std": 0.04}),
        )
        errors.append(cal.rho / s.rho - 1.0)
    assert abs(np.mean(errors)) < 0.01


def test_nuisances_do_not_move_an_exact_scene() -> None:
    s = draw_scene(SceneConfig.surveillance(noise_px=0.0, height_std_m=0.0, n_people=50), np.random.default_rng(8))
    exact = {**ideal(s), "height_std_m": 1e-6}
    for name, value in (
        ("aspect_std", 0.01),
        ("keypoint_bias_std", 0.002),
        ("lens_corner_std", 0.03),
        ("mean_height_std", 0.04),
    ):
        cal = calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, 1.7, **{**exact, name: value}))
        assert cal.fx == pytest.approx(s.fx, rel=1e-6), name
        assert angle_deg(cal.normal, s.normal) < 1e-5 and cal.rho == pytest.approx(s.rho, rel=1e-6), name
        assert cal.uncertainty is not None and cal.uncertainty.covariance.shape == (8, 8)


def test_consider_covariance_holds_the_prior_and_adds_its_effect() -> None:
    layout = Layout.build(True, None, Priors(None, 0.01, 0.003, None, 0.04, 0.05), estimate_k=False)
    assert set(layout.considered) == {"aspect", "bias"}
    rng = np.random.default_rng(0)
    a = rng.normal(size=(40, len(layout.names)))
    s = a.T @ a + np.diag(np.where(np.isfinite(layout.prior_std), layout.prior_std, np.inf) ** -2.0)
    cov = _consider_covariance(layout, s)
    e, c = layout.estimated, ~layout.estimated
    np.testing.assert_allclose(np.diag(cov)[c], layout.prior_std[c] ** 2)
    # Holding the considered parameters costs accuracy the plain posterior would not show.
    assert np.all(np.diag(cov)[e] >= np.diag(np.linalg.inv(s[np.ix_(e, e)])) - 1e-15)
    np.testing.assert_allclose(cov, cov.T)
    assert np.linalg.eigvalsh(cov).min() > -1e-12


def test_leaning_individuals_do_not_pull_the_camera_along_what_people_cannot_determine() -> None:
    """Thirty walkers, each with their own persistent 2 degree lean, each seen 24 times as they cross the view.

    Every camera that keeps the vertical vanishing point and the horizon (the principal point moved across the
    horizon, f and the tilt with it) explains these images equally well, so only the priors choose among them.
    A lean prior in world radians did: a steeper view foreshortens the people and so needs smaller leans for
    the same image, and the fit took it (f 4 % short, cy 63 px up, the ground 1.3 degrees off). Nothing may move the
    camera off the truth, which sits at the principal point prior's centre.
    """
    rng = np.random.default_rng(5)
    camera = CameraPose(focal_px=1400.0, position_m=(0.0, 0.0, 6.0), pitch_deg=25.0, roll_deg=1.0)
    tops, bottoms, tracks = [], [], []
    for person in range(30):
        start = camera.ground_point_at((rng.uniform(150, 1770), rng.uniform(300, 1000)))[:2]
        heading = rng.uniform(0, 2 * np.pi)
        walk = start + np.outer(np.arange(24) * 0.6, (np.sin(heading), np.cos(heading)))
        lean = np.radians(rng.normal(0.0, 2.0)) * rng.choice((-1.0, 1.0), 2) * rng.uniform(0.3, 1.0, 2)
        height = rng.normal(1.32, 0.07)
        feet = np.column_stack((walk, np.zeros(len(walk))))
        shoulders = feet + np.append(height * np.tan(lean), height)
        b_px, _ = camera.project(feet)
        t_px, _ = camera.project(shoulders)
        seen = np.all((b_px > 0) & (b_px < (1920, 1080)) & (t_px > 0) & (t_px < (1920, 1080)), axis=1)
        tops.append(t_px[seen])
        bottoms.append(b_px[seen])
        tracks += [person] * int(seen.sum())
    tops_px = np.vstack(tops) + rng.normal(0.0, 0.3, (len(tracks), 2))
    bottoms_px = np.vstack(bottoms) + rng.normal(0.0, 0.3, (len(tracks), 2))
    cal = calibrate(tops_px, bottoms_px, CalibrationProblem(camera.image_size, 1.32, ankle_height_m=0.0), tracks=tracks)
    assert cal.individuals >= 25
    assert cal.fx == pytest.approx(camera.focal_px, rel=0.015)
    assert abs(cal.cy - 540.0) < 15.0
    assert angle_deg(cal.normal, camera.normal) < 0.3


def test_individuals_sums_are_np_add_at_in_observation_order() -> None:
    rng = np.random.default_rng(2)
    blocks, track = rng.normal(size=(300, 2, 13)), rng.integers(0, 90, 300)
    expected = np.zeros((95, 2, 13))
    np.add.at(expected, track, blocks)
    np.testing.assert_array_equal(_track_sums(blocks, track, 95), expected)
