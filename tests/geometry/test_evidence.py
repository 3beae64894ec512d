"""Collapsing repeated observations: still people and static false detections count once, walkers fully."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.geometry import CalibrationProblem
from service.geometry.evidence import balanced_sample, collapse_repeats, repeat_radius_px, solve_evidence
from tests.support.geometry import scene


def test_a_static_detection_with_jitter_collapses_and_walkers_survive() -> None:
    rng = np.random.default_rng(0)
    # A mannequin in 80 frames: the same segment with 1 px keypoint jitter.
    mannequin_top = np.array([50.0, 300.0]) + rng.normal(0, 1.0, (80, 2))
    mannequin_bottom = np.array([52.0, 450.0]) + rng.normal(0, 1.0, (80, 2))
    # A walker crossing at 6 px per frame for 40 frames.
    steps = np.arange(40)[:, None] * np.array([6.0, 1.0])
    walker_top, walker_bottom = np.array([400.0, 500.0]) + steps, np.array([402.0, 700.0]) + steps
    tops = np.vstack([mannequin_top, walker_top])
    bottoms = np.vstack([mannequin_bottom, walker_bottom])
    keep = collapse_repeats(tops, bottoms, radius_px=4.4)
    kept_mannequin = int(np.sum(keep < 80))
    assert 1 <= kept_mannequin <= 3
    assert np.sum(keep >= 80) == 40
    assert keep[0] == 0 and np.all(np.diff(keep) > 0)  # the first of a group, in input order


def test_same_spot_different_people_are_both_kept() -> None:
    tops = np.array([[100.0, 100.0], [100.0, 130.0]])  # a tall and a short person on the same ankle spot
    bottoms = np.array([[100.0, 400.0], [100.0, 400.0]])
    assert collapse_repeats(tops, bottoms, radius_px=4.0).tolist() == [0, 1]


def test_non_finite_rows_and_empty_input() -> None:
    tops = np.array([[np.nan, 1.0], [10.0, 10.0], [10.5, 10.5]])
    bottoms = np.array([[1.0, 2.0], [10.0, 90.0], [10.5, 90.5]])
    assert collapse_repeats(tops, bottoms, radius_px=2.0).tolist() == [0, 1]
    assert collapse_repeats(np.zeros((0, 2)), np.zeros((0, 2)), radius_px=2.0).tolist() == []
    assert repeat_radius_px((1920, 1080)) == np.float64(0.002 * np.hypot(1920, 1080))


def _greedy_reference(points: np.ndarray, radius_px: float) -> list[int]:
    """The rule of `collapse_repeats`, written out by brute force: in input order, an observation is kept unless a
    kept one lies within the radius in every coordinate (non-finite rows are kept)."""
    finite_kept: list[int] = []
    kept: list[int] = []
    for i, point in enumerate(points):
        if not np.all(np.isfinite(point)):
            kept.append(i)
        elif not any(np.max(np.abs(points[k] - point)) <= radius_px for k in finite_kept):
            finite_kept.append(i)
            kept.append(i)
    return kept


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(*[st.integers(0, 6)] * 4).map(lambda xs: [float(x) for x in xs]) | st.just([np.nan, 0.0, 0.0, 0.0]),
        max_size=40,
    ),
    st.sampled_from([0.5, 1.0, 2.0, 3.0]),
)
def test_collapse_repeats_is_the_greedy_rule_also_at_the_radius_itself(
    rows: list[list[float]], radius_px: float
) -> None:
    # Integer coordinates on a small grid: many exact repeats, chains of neighbours (a near b near c, a not near
    # c) and distances exactly at the radius, where the kept set depends on the order and the inclusive bound.
    points = np.array(rows, dtype=float).reshape(-1, 4)
    keep = collapse_repeats(points[:, :2], points[:, 2:], radius_px=radius_px)
    assert keep.tolist() == _greedy_reference(points, radius_px)


def test_balanced_sample_keeps_everything_under_the_cap_and_spreads_over_the_image_above_it() -> None:
    rng = np.random.default_rng(1)
    crowd = rng.normal((300.0, 900.0), 20.0, (900, 2))  # everyone lingering in one spot, bottom left
    scattered = rng.uniform((0.0, 0.0), (1920.0, 1080.0), (100, 2))
    bottoms = np.vstack([crowd, scattered])
    assert balanced_sample(bottoms, (1920, 1080), cap=1000).tolist() == list(range(1000))
    chosen = balanced_sample(bottoms, (1920, 1080), cap=200)
    assert len(chosen) == 200 and len(set(chosen.tolist())) == 200 and np.all(np.diff(chosen) > 0)
    # Water-filling: the scattered people (1-4 per cell) are nearly all kept, the crowd gets what they leave
    # (a scattered person inside the crowd's cell competes with the crowd, hence not all 100).
    assert np.sum(chosen >= 900) >= 95
    assert np.array_equal(chosen, balanced_sample(bottoms, (1920, 1080), cap=200))  # reproducible
    assert not np.array_equal(chosen, balanced_sample(bottoms, (1920, 1080), cap=200, seed=1))


def test_solve_evidence_collapses_repeats_and_maps_inliers_back() -> None:
    truth = scene(3, surveillance=True, n_people=60)
    # A mannequin seen in 50 frames: the same segment, repeated, must count once among the people used.
    tops = np.vstack([truth.tops_px, np.repeat(truth.tops_px[:1], 50, axis=0)])
    bottoms = np.vstack([truth.bottoms_px, np.repeat(truth.bottoms_px[:1], 50, axis=0)])
    solve = solve_evidence(tops, bottoms, CalibrationProblem(truth.image_size, 1.7 * 0.78, equal_focal=True))
    assert solve.calibration is not None and solve.error is None
    assert solve.people_used == 60 and solve.used.tolist() == list(range(60))
    assert abs(solve.calibration.fx / truth.fx - 1) < 0.1
    mask = solve.inlier_mask(len(tops))
    assert mask.sum() == solve.calibration.num_inliers >= 50 and not mask[60:].any()
    capped = solve_evidence(tops, bottoms, CalibrationProblem(truth.image_size, 1.7 * 0.78), cap=30)
    assert capped.people_used == 30 and capped.calibration is not None


def test_solve_evidence_reports_why_it_cannot_calibrate() -> None:
    tops = np.array([[100.0, 100.0], [400.0, 120.0]])
    bottoms = np.array([[100.0, 300.0], [400.0, 330.0]])
    solve = solve_evidence(tops, bottoms, CalibrationProblem((640, 480)))
    assert solve.calibration is None and solve.error and solve.people_used == 2
    assert not solve.inlier_mask(2).any()
