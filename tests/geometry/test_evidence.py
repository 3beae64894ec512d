"""Collapsing repeated observations: still people and static false detections count once, walkers fully."""

from __future__ import annotations

import numpy as np

from service.geometry.evidence import collapse_repeats, repeat_radius_px


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
