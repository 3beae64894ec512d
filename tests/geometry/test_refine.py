"""The MAP fit's structure: one height per individual, consider parameters, no shrinking world, exact when exact."""

from __future__ import annotations

import numpy as np
import pytest

from bench.simulate import SceneConfig, draw_scene
from service.geometry import CalibrationProblem, calibrate
from service.geometry.model import Layout, Priors
from service.geometry.refine import _consider_covariance
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
