"""The generic RANSAC loop on a toy problem that has nothing to do with cameras: fitting a 2-D line."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry import CalibrationError
from service.geometry.ransac import Hypotheses, RansacOptions, draw_samples, ransac, required_iterations


def _line_problem(points: np.ndarray, threshold: float):  # type: ignore[no-untyped-def]
    """propose: the line through two points as (unit normal, offset); score: truncated squared distance."""

    def propose(samples: np.ndarray) -> Hypotheses:
        a, b = points[samples[:, 0]], points[samples[:, 1]]
        d = b - a
        length = np.hypot(d[:, 0], d[:, 1])
        ok = length > 1e-12
        normal = np.stack((-d[ok, 1], d[ok, 0]), 1) / length[ok, None]
        return normal, -np.sum(normal * a[ok], 1)

    def score(hypotheses: Hypotheses) -> np.ndarray:
        normal, offset = hypotheses
        distance = points @ normal.T + offset  # (N, M)
        return np.minimum((distance.T / threshold) ** 2, 1.0)

    return propose, score


def _noisy_line(rng: np.random.Generator, n_in: int, n_out: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    t = rng.uniform(-10, 10, n_in)
    inliers = np.stack((t, 0.5 * t + 2.0), 1) + rng.normal(0, noise, (n_in, 2))
    outliers = rng.uniform(-10, 10, (n_out, 2))
    truth = np.r_[np.ones(n_in, bool), np.zeros(n_out, bool)]
    return np.vstack((inliers, outliers)), truth


@pytest.mark.parametrize("outlier_share", [0.0, 0.5, 0.8])
def test_finds_the_line_among_outliers(outlier_share: float) -> None:
    rng = np.random.default_rng(3)
    n_out = round(200 * outlier_share / (1 - outlier_share))
    points, truth = _noisy_line(rng, 200, n_out, noise=0.05)
    propose, score = _line_problem(points, threshold=0.2)
    found = ransac(len(points), 2, propose, score, RansacOptions(), np.random.default_rng(0))
    normal, offset = found.model
    # y = 0.5 x + 2  <=>  (-0.5, 1) . p - 2 = 0, up to sign and scale.
    expected = np.array([-0.5, 1.0, -2.0]) / np.hypot(0.5, 1.0)
    got = np.r_[normal, offset] * np.sign(normal[1])
    np.testing.assert_allclose(got, expected, atol=0.05)
    assert found.inliers[truth].mean() > 0.95
    assert found.inliers[~truth].sum() <= 0.1 * max(n_out, 1)


def test_stops_as_soon_as_a_better_sample_is_unlikely() -> None:
    points, _ = _noisy_line(np.random.default_rng(1), 100, 0, noise=0.0)
    propose, score = _line_problem(points, threshold=0.1)
    clean = ransac(len(points), 2, propose, score, RansacOptions(batch=16), np.random.default_rng(0))
    assert clean.iterations == 16  # one batch: every sample is all-inlier, so one draw already suffices
    points, _ = _noisy_line(np.random.default_rng(1), 60, 140, noise=0.0)
    propose, score = _line_problem(points, threshold=0.1)
    dirty = ransac(len(points), 2, propose, score, RansacOptions(batch=16), np.random.default_rng(0))
    # 30 % inliers, samples of 2, 99.9 %: log(0.001) / log(1 - 0.09) = 73.2 -> 74 draws, in whole batches of 16.
    assert required_iterations(0.3, 2, 0.999) == 74
    assert dirty.iterations == 80


def test_same_seed_same_answer_and_no_hypothesis_raises() -> None:
    points, _ = _noisy_line(np.random.default_rng(2), 30, 30, noise=0.05)
    propose, score = _line_problem(points, threshold=0.2)
    a = ransac(len(points), 2, propose, score, RansacOptions(), np.random.default_rng(5))
    b = ransac(len(points), 2, propose, score, RansacOptions(), np.random.default_rng(5))
    np.testing.assert_array_equal(a.costs, b.costs)
    same = np.zeros((10, 2))
    propose, score = _line_problem(same, threshold=0.2)  # every pair coincides: no line is ever proposed
    with pytest.raises(CalibrationError, match="no valid hypothesis"):
        ransac(len(same), 2, propose, score, RansacOptions(max_iterations=64), np.random.default_rng(0))
    with pytest.raises(CalibrationError, match="at least 2"):
        ransac(1, 2, propose, score, RansacOptions(), np.random.default_rng(0))


def test_samples_hold_distinct_indices() -> None:
    samples = draw_samples(np.random.default_rng(0), 3, 3, 500)
    assert np.all(np.sort(samples, 1) == np.arange(3))
