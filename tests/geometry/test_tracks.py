"""Linking observations into individuals: walkers keep one label, people who only pass each other do not merge."""

from __future__ import annotations

import numpy as np
import pytest

from service.geometry.tracks import link_tracks


def _walker(start: tuple[float, float], step: tuple[float, float], length_px: float, frames: int) -> np.ndarray:
    bottoms = np.array(start) + np.arange(frames)[:, None] * np.array(step)
    tops = bottoms - np.array([0.0, length_px])
    return np.stack((tops, bottoms), 1)


def test_walkers_keep_one_label_each_in_any_order() -> None:
    # 25 fps, a 150 px tall person walking 5 px a frame and a 80 px one 3 px a frame, 20 frames each.
    a, b = _walker((300, 800), (5, -1), 150, 20), _walker((1200, 400), (-3, 0.5), 80, 20)
    times = np.tile(np.arange(20) / 25.0, 2)
    points = np.concatenate((a, b))
    order = np.random.default_rng(0).permutation(40)
    labels = link_tracks(times[order], points[order, 0], points[order, 1])
    back = np.empty(40, dtype=int)
    back[order] = labels
    assert len(set(back[:20])) == 1 and len(set(back[20:])) == 1 and back[0] != back[20]


def test_gates_split_what_could_not_be_one_person() -> None:
    people = _walker((500, 600), (4, 0), 120, 3)
    times = np.array([0.0, 0.04, 0.08])
    # Too far in one frame (300 px at 120 px per 1.32 m: 3.3 m in 40 ms), a different size, and a long gap.
    jump = people.copy()
    jump[1] += (300.0, 0.0)
    shrunk = people.copy()
    shrunk[1, 0] = shrunk[1, 1] - (0.0, 60.0)
    assert len(set(link_tracks(times, people[:, 0], people[:, 1]))) == 1
    assert len(set(link_tracks(times, jump[:, 0], jump[:, 1]))) >= 2
    assert len(set(link_tracks(times, shrunk[:, 0], shrunk[:, 1]))) >= 2
    assert len(set(link_tracks(np.array([0.0, 5.0, 10.0]), people[:, 0], people[:, 1]))) == 3


def test_people_in_one_frame_are_never_linked_and_crossings_stay_apart() -> None:
    # Two people side by side in every frame, swapping nothing: two labels, never one.
    left, right = _walker((400, 700), (3, 0), 140, 10), _walker((440, 700), (3, 0), 140, 10)
    times = np.tile(np.arange(10) * 0.04, 2)
    points = np.concatenate((left, right))
    labels = link_tracks(times, points[:, 0], points[:, 1])
    assert len(set(labels)) == 2 and len(set(labels[:10])) == 1
    # Equal times never link.
    assert len(set(link_tracks(np.zeros(2), points[[0, 10], 0], points[[0, 10], 1]))) == 2


def test_bad_rows_get_their_own_label_and_shapes_are_checked() -> None:
    points = _walker((500, 600), (4, 0), 120, 3)
    points[1, 0] = np.nan
    labels = link_tracks([0.0, 0.04, 0.08], points[:, 0], points[:, 1])
    assert len(set(labels)) == 3 or labels[1] not in labels[[0, 2]]
    with pytest.raises(ValueError, match="same"):
        link_tracks([0.0], points[:, 0], points[:, 1])
