"""Refinement and uncertainty: the ML polish helps, and the reported sigmas mean what they say."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import SolveOptions
from service.geometry.measure import measure
from tests.support.geometry import ideal, pairwise_distances, scene, solve


def _distance_errors(cal, s) -> np.ndarray:  # type: ignore[no-untyped-def]
    d = pairwise_distances(cal.points_bottom)
    t = pairwise_distances(s.points_bottom)
    iu = np.triu_indices(len(t), 1)
    return np.abs(d[iu] - t[iu]) / t[iu]  # NaN for people the calibration rejected


def test_refinement_improves_distances_under_height_spread() -> None:
    linear, refined = [], []
    for seed in range(20):
        s = scene(seed, surveillance=True, n_people=60)
        # Like for like: both under the linear solver's assumptions (principal point at the centre, no lens).
        linear.append(np.nanmean(_distance_errors(solve(s, SolveOptions(refine=False), **ideal(s)), s)))
        refined.append(np.nanmean(_distance_errors(solve(s, **ideal(s)), s)))
    assert np.mean(refined) < np.mean(linear)


def test_reported_sigmas_are_calibrated() -> None:
    """About 68 % of true errors fall within 1 sigma, for f, rho and every pairwise distance, when the model
    matches the simulator (on real-camera mismatches: tests/geometry/test_coverage.py)."""
    z_f, z_rho, z_dist = [], [], []
    for seed in range(60):
        s = scene(seed, surveillance=True, n_people=25)
        cal = solve(s, SolveOptions(seed=seed), **ideal(s))
        assert cal.uncertainty is not None
        z_f.append((cal.fx - s.fx) / cal.uncertainty.fx_px)
        z_rho.append((cal.rho - s.rho) / cal.uncertainty.rho_m)
        m = measure(cal, s.tops_px, s.bottoms_px)
        t = pairwise_distances(s.points_bottom)
        iu = np.triu_indices(len(t), 1)
        z_dist.append((m.distances_m[iu] - t[iu]) / m.distance_std_m[iu])
    within = [np.mean(np.abs(z) < 1) for z in (np.array(z_f), np.array(z_rho), np.concatenate(z_dist))]
    for frac in within:
        assert 0.5 < frac < 0.85, within


def test_uncertainty_grows_with_noise_and_shrinks_with_people() -> None:
    def sigma(**kw: object) -> float:
        s = scene(4, surveillance=True, **kw)
        cal = solve(s, **ideal(s))  # with the principal point free its prior, not the people, bounds f
        assert cal.uncertainty is not None
        return cal.uncertainty.fx_px / cal.fx

    assert sigma(noise_px=4.0, n_people=30) > sigma(noise_px=0.5, n_people=30)
    assert sigma(n_people=200) < sigma(n_people=20)


def test_noise_free_scene_has_negligible_uncertainty() -> None:
    s = scene(2, noise_px=0.0, n_people=20)
    # The simulated heights are exact: said so, noise-free people determine the camera. (A height spread the
    # solver must allow for keeps f uncertain however perfect the pixels: each person's height is unknown.)
    cal = solve(s, equal_focal=False, height_std_m=1e-6, **ideal(s))
    assert cal.uncertainty is not None
    assert cal.uncertainty.fx_px < 1e-3 * cal.fx
    assert cal.uncertainty.normal_deg < 0.01


def test_people_without_ankles_are_placed_from_shoulders_with_larger_sigma() -> None:
    s = scene(6, surveillance=True, n_people=30)
    # The principal point given: otherwise its prior dominates both people's sigma and the comparison.
    cal = solve(s, **ideal(s))
    bottoms = s.bottoms_px.copy()
    bottoms[0] = np.nan
    both = measure(cal, s.tops_px, s.bottoms_px)
    hidden = measure(cal, s.tops_px, bottoms)
    assert not hidden.from_ankles[0] and hidden.from_ankles[1:].all()
    assert np.all(np.isfinite(hidden.points_bottom[0]))
    # Placed from the shoulders, the person lands near the truth (within their height deviation's effect)...
    assert np.linalg.norm(hidden.points_bottom[0] - s.points_bottom[0]) < 0.15 * np.linalg.norm(s.points_bottom[0])
    # ... with a larger uncertainty than from the ankles.
    assert np.all(hidden.distance_std_m[0, 1:] > both.distance_std_m[0, 1:])
    np.testing.assert_allclose(hidden.distances_m[1:, 1:], both.distances_m[1:, 1:])


def test_unplaceable_people_give_nan_not_errors() -> None:
    s = scene(6, surveillance=True, n_people=5)
    cal = solve(s)
    tops, bottoms = s.tops_px.copy(), s.bottoms_px.copy()
    tops[1] = bottoms[1] = np.nan
    m = measure(cal, tops, bottoms)
    assert not m.placed[1] and m.placed[[0, 2, 3, 4]].all()
    assert np.isnan(m.distances_m[1, 0]) and np.isfinite(m.distances_m[0, 2])


@pytest.mark.parametrize("equal_focal", [True, False])
def test_covariance_is_symmetric_positive_semidefinite(equal_focal: bool) -> None:
    s = scene(1, n_people=30, noise_px=1.0, square_pixels=equal_focal)
    cal = solve(s, equal_focal=equal_focal, aspect_std=0.0)  # exactly square pixels: fx and fy move together
    assert cal.uncertainty is not None
    cov = cal.uncertainty.covariance
    np.testing.assert_allclose(cov, cov.T, rtol=1e-6, atol=1e-12)
    assert np.linalg.eigvalsh(cov).min() > -1e-9 * np.abs(cov).max()
    if equal_focal:
        assert cov[0, 0] == pytest.approx(cov[1, 1]) == pytest.approx(cov[0, 1])
