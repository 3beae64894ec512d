"""RANSAC: exact minimal solver, vectorised scoring, outlier rejection, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from bench.simulate import OUTLIER_KINDS
from service.geometry import SolveOptions
from service.geometry.camera import ImageFrame
from service.geometry.consensus import ConsensusSettings, score_hypotheses
from service.geometry.minimal import solve_minimal
from service.geometry.ransac import RansacOptions, required_iterations
from service.geometry.vec import homogeneous
from tests.support.geometry import angle_deg, scene, solve


@pytest.mark.parametrize("equal_focal", [True, False])
def test_minimal_solver_is_exact_for_every_sample(equal_focal: bool) -> None:
    s = scene(21, noise_px=0.0, n_people=12, square_pixels=equal_focal)
    frame = ImageFrame.from_size(s.image_size)
    t, b = homogeneous(frame.normalise(s.tops_px)), homogeneous(frame.normalise(s.bottoms_px))
    m = 2 if equal_focal else 3
    samples = np.array([np.random.default_rng(i).choice(12, m, replace=False) for i in range(50)])
    focal, normal, rho, _ = solve_minimal(t[samples], b[samples], 1.7, equal_focal, None)
    np.testing.assert_allclose(focal[:, 0] * frame.scale_px, s.fx, rtol=1e-7)
    np.testing.assert_allclose(focal[:, 1] * frame.scale_px, s.fy, rtol=1e-7)
    np.testing.assert_allclose(normal, np.broadcast_to(s.normal, normal.shape), atol=1e-8)
    np.testing.assert_allclose(rho, s.rho, rtol=1e-7)


def test_scoring_flags_exactly_the_corrupted_people() -> None:
    s = scene(8, noise_px=0.0, n_people=40, outlier_fraction=0.25)
    frame = ImageFrame.from_size(s.image_size)
    costs = score_hypotheses(
        frame.normalise(s.tops_px),
        frame.normalise(s.bottoms_px),
        np.array([[s.fx, s.fy]]) / frame.scale_px,
        s.normal[None],
        np.array([s.rho]),
        1.7,
        frame.scale_px,
        ConsensusSettings(inlier_px=3.0),
    )[0]
    assert np.all(costs[~s.outliers] < 1e-12)  # perfect people cost nothing
    assert np.all(costs[s.outliers] > 0)


@pytest.mark.parametrize("equal_focal", [True, False])
def test_survives_thirty_percent_outliers(equal_focal: bool) -> None:
    errors_clean, errors_dirty, leaked = [], [], []
    for seed in range(12):
        kw = {"n_people": 60, "noise_px": 0.5, "height_std_m": 0.07, "square_pixels": equal_focal}
        clean = scene(seed, **kw)
        dirty = scene(seed, outlier_fraction=0.3, **kw)
        a = solve(clean, SolveOptions(seed=seed), equal_focal=equal_focal)
        c = solve(dirty, SolveOptions(seed=seed), equal_focal=equal_focal)
        errors_clean.append(abs(a.fx / clean.fx - 1))
        errors_dirty.append(abs(c.fx / dirty.fx - 1))
        leaked.append(c.inliers[dirty.outliers].mean())
        assert c.inliers[~dirty.outliers].mean() > 0.9
        assert angle_deg(c.normal, dirty.normal) < 3.0
    assert np.mean(errors_dirty) < 3 * np.mean(errors_clean) + 0.01
    assert np.mean(leaked) < 0.3


def test_outlier_kinds_are_rejected() -> None:
    """Sitting people and random detections are caught by the height and direction tests."""
    s = scene(3, noise_px=0.5, n_people=80, outlier_fraction=0.4)
    cal = solve(s, equal_focal=False)
    idx = np.flatnonzero(s.outliers)
    for k, kind in enumerate(OUTLIER_KINDS):
        if kind in ("sitting", "bad_detection"):
            assert not cal.inliers[idx[k :: len(OUTLIER_KINDS)]].any(), kind


def test_stops_early_on_clean_data_and_uses_more_iterations_on_dirty() -> None:
    clean = scene(5, noise_px=0.5, n_people=100)
    dirty = scene(5, noise_px=0.5, n_people=100, outlier_fraction=0.7)
    a = solve(clean, SolveOptions(refine=False), equal_focal=False)
    b = solve(dirty, SolveOptions(refine=False), equal_focal=False)
    assert a.ransac_iterations <= RansacOptions().batch
    # 30 % inliers, samples of 3, 99.9 % confidence: log(0.001) / log(1 - 0.3^3) = 253 draws.
    assert b.ransac_iterations >= 253
    assert required_iterations(0.3, 3, 0.999) == 253
