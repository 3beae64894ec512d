"""Linking observations into individuals: walkers keep one label, people who only pass each other do not merge."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.simulate import camera_normal, project
from service.geometry.tracks import _Gates, link_tracks


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


# A Town-Centre-like camera (1920x1080, f 2700 px, 7.8 m up, 20 deg down) seeing 1.32 m segments at 25 fps.
_FPS = 25.0
_HEIGHT_M = 1.32
_JITTER = 0.01
_MEASURED_JITTER = 0.007


def _street_camera() -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    normal = camera_normal(20.0, 0.0)
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    forward /= np.linalg.norm(forward)
    return normal, forward, np.cross(normal, forward), 7.8


def _seen(ground_m: np.ndarray, rng: np.random.Generator | None = None, jitter: float = 0.0) -> np.ndarray:
    """(n, 2, 2) shoulder and ankle pixels of people standing at ground_m (n, 2): (sideways, ahead) metres, with
    keypoint jitter of `jitter` x the segment length."""
    normal, forward, side, rho = _street_camera()
    feet = -rho * normal + ground_m[:, :1] * side + ground_m[:, 1:] * forward
    tops_px = project(feet + _HEIGHT_M * normal, 2700.0, 2700.0, 960.0, 540.0)
    bottoms_px = project(feet, 2700.0, 2700.0, 960.0, 540.0)
    if rng is not None:
        size = np.linalg.norm(tops_px - bottoms_px, axis=1, keepdims=True)
        tops_px = tops_px + rng.normal(0.0, jitter, tops_px.shape) * size
        bottoms_px = bottoms_px + rng.normal(0.0, jitter, bottoms_px.shape) * size
    return np.stack((tops_px, bottoms_px), 1)


def _path(start_m: tuple[float, float], velocity_m_s: tuple[float, float], times_s: np.ndarray) -> np.ndarray:
    return np.array(start_m) + (times_s - times_s[0])[:, None] * np.array(velocity_m_s)


def test_a_stranger_appearing_nearer_in_depth_is_not_the_walker_who_vanished() -> None:
    # The Town Centre defect (there 6.2 m in 0.44 s): a walker 35 m away crosses slowly to the right and is hidden
    # at 3.2 s; 0.44 s later a stranger appears 5 m nearer, at the same place in the image's horizontal, and walks
    # on. In pixels the stranger is under one segment length below the vanished walker: an isotropic speed gate
    # (3 m/s in units of l / 1.32 m) took them for one person moving 11 m/s in depth.
    first_s = np.arange(0, 81) / _FPS
    second_s = np.arange(91, 126) / _FPS
    walker = _path((0.0, 35.0), (0.6, 0.0), first_s)
    stranger = _path((walker[-1, 0], 30.0), (0.6, 0.3), second_s)
    points = _seen(np.concatenate((walker, stranger)))
    times = np.concatenate((first_s, second_s))
    labels = link_tracks(times, points[:, 0], points[:, 1])
    assert len(set(labels[: len(first_s)])) == 1 and len(set(labels[len(first_s) :])) == 1
    assert labels[0] != labels[-1]


@settings(max_examples=40, deadline=None)
@given(
    heading_deg=st.floats(0.0, 360.0),
    speed_m_s=st.floats(0.6, 2.0),
    ahead_m=st.floats(14.0, 35.0),
    gap_frames=st.integers(1, 24),
    seed=st.integers(0, 2**16),
)
def test_one_walker_keeps_one_label_through_a_gap(
    heading_deg: float, speed_m_s: float, ahead_m: float, gap_frames: int, seed: int
) -> None:
    # Seen for 1.2 s, hidden for up to 1 s (an occlusion), seen for 1.2 s more. Keypoint jitter 0.7 % of the segment
    # per coordinate, the top of what Town Centre shows (0.4-0.7 %, robust, from second differences). At 1 % the
    # first link, which has no velocity to check, fails on rare corners of this space (2 m/s, the single-sighting
    # gate's walking pace, 14 m ahead, a 3-sigma draw: 15 of 3 840 corner cases, 0 at 0.7 %), which hypothesis
    # finds: the walker's first sighting becomes an individual of its own (independence lost, no bias).
    heading = np.radians(heading_deg)
    frames = np.concatenate((np.arange(30), 30 + gap_frames + np.arange(30)))
    times = frames / _FPS
    ground = np.array((0.0, ahead_m)) + times[:, None] * speed_m_s * np.array((np.cos(heading), np.sin(heading)))
    points = _seen(ground, np.random.default_rng(seed), _MEASURED_JITTER)
    assert len(set(link_tracks(times, points[:, 0], points[:, 1]))) == 1


@settings(max_examples=25, deadline=None)
@given(
    speed_m_s=st.floats(0.8, 1.6),
    radius_m=st.floats(1.0, 4.0),
    direction=st.sampled_from((-1.0, 1.0)),
    ahead_m=st.floats(14.0, 30.0),
    seed=st.integers(0, 2**16),
)
def test_a_turning_walker_keeps_one_label(
    speed_m_s: float, radius_m: float, direction: float, ahead_m: float, seed: int
) -> None:
    # Walking straight, then a 90-180 deg turn on a circle (centripetal v^2 / r up to 2.6 m/s^2), then straight.
    times = np.arange(100) / _FPS
    turn_s = np.pi * radius_m / speed_m_s
    angle = direction * np.clip(times - 1.0, 0.0, turn_s) * speed_m_s / radius_m
    step = speed_m_s / _FPS * np.stack((np.cos(angle), np.sin(angle)), 1)
    ground = np.array((0.0, ahead_m)) + np.cumsum(step, axis=0)
    points = _seen(ground, np.random.default_rng(seed), _JITTER)
    assert len(set(link_tracks(times, points[:, 0], points[:, 1]))) == 1


def test_crossing_walkers_keep_their_own_labels_when_one_hides_the_other() -> None:
    # Two walkers cross in an X 20 m away; while the nearer passes in front, the farther is hidden for 0.4 s.
    times = np.arange(75) / _FPS
    a = _path((-2.0, 19.0), (1.4, 0.5), times)
    b = _path((2.0, 19.0), (-1.4, 0.5), times)
    hidden = (times > 1.2) & (times < 1.6)
    keep = np.concatenate((np.ones(75, bool), ~hidden))
    points = _seen(np.concatenate((a, b)), np.random.default_rng(3), 0.01)[keep]
    labels = link_tracks(np.concatenate((times, times))[keep], points[:, 0], points[:, 1])
    first, second = labels[:75], labels[75:]
    assert len(set(first)) == 1 and len(set(second)) == 1 and first[0] != second[0]


@pytest.mark.parametrize(("spacing_s", "most_linked"), [(0.5, 0.25), (1.0, 0.0)])
def test_busy_low_frame_rate_strangers_are_rarely_merged(spacing_s: float, most_linked: float) -> None:
    # Ten different people in every frame, frames 0.5 or 1 s apart (a 2 or 1 fps stream of a busy street, 14-35 m
    # away): nobody is seen twice, so every link is a wrong one. Without a velocity a link is a guess: made only
    # across short gaps (none at 1 fps) and at a walking pace. The isotropic speed gate linked 73 % (2 fps) and
    # 65 % (1 fps) of these observations to a stranger.
    rng = np.random.default_rng(7)
    frames = 40
    ground = np.stack((rng.uniform(-8.0, 8.0, (frames, 10)), rng.uniform(14.0, 35.0, (frames, 10))), -1)
    points = _seen(ground.reshape(-1, 2))
    times = np.repeat(np.arange(frames) * spacing_s, 10)
    labels = link_tracks(times, points[:, 0], points[:, 1])
    assert 1.0 - len(set(labels)) / len(labels) <= most_linked


def test_tracks_judged_together_get_the_costs_each_gets_alone() -> None:
    # Tracks with windows of different lengths (one sighting, a short and a long history, one past the velocity's
    # window) are judged in one batch against a frame: each row must be what that track alone gets.
    rng = np.random.default_rng(3)
    walkers = [_walker((300 + 200 * k, 700 - 30 * k), (4 - k, 1), 120 + 10 * k, 12) for k in range(4)]
    times = np.tile(np.arange(12) / 10.0, 4)
    points = np.concatenate(walkers) + rng.normal(0.0, 0.5, (48, 2, 2))
    segment = points[:, 0] - points[:, 1]
    gates = _Gates(times, points[:, 1], segment, np.hypot(*segment.T), 1.32, 3.0, 1.25)
    tracks = [[10], [18, 19, 20, 21], [24, 25, 26, 27, 28, 29, 30, 31, 32, 33], [40, 42, 43]]
    current = np.array([12 * k + 11 for k in range(4)])  # every walker's 12th sighting

    def costs(judged: list[list[int]]) -> np.ndarray:
        return gates.costs(judged, [times[t].tolist() for t in judged], np.array([t[-1] for t in judged]), current)

    together = costs(tracks)
    alone = np.stack([costs([track])[0] for track in tracks])
    np.testing.assert_array_equal(together, alone)
    assert np.isfinite(np.diag(together)).all()  # each walker's own next sighting passes its gates
