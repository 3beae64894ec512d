"""Linking across gaps of seconds by appearance: one walker's sightings joined, strangers and overlaps refused."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.geometry.appearance import (
    APPEARANCE_REGIONS,
    REGION_BINS,
    appearance_distances,
    decode_descriptors,
    encode_descriptor,
)
from service.geometry.tracks import LONG_MAX_GAP_S, MAX_APPEARANCE_DISTANCE, link_tracks
from tests.support.geometry import sightings

REGIONS = len(APPEARANCE_REGIONS)


def _look(seed: int) -> np.ndarray:
    """A person's (regions, bins) colour histograms: a few dominant colours, as clothes have."""
    rng = np.random.default_rng(seed)
    return rng.dirichlet(np.full(REGION_BINS, 0.05), size=REGIONS)


def _seen(look: np.ndarray, seed: int, noise: float = 0.1) -> bytes:
    """One sighting's descriptor: the look with the histogram noise of another frame (light, pose, pixels)."""
    rng = np.random.default_rng(seed)
    return encode_descriptor(look * rng.uniform(1.0 - noise, 1.0 + noise, size=look.shape) + 1e-4)


def _walker(
    times_s: np.ndarray, start_px: tuple[float, float], velocity_px_s: tuple[float, float], length_px: float
) -> tuple[np.ndarray, np.ndarray]:
    bottoms = np.array(start_px) + times_s[:, None] * np.array(velocity_px_s)
    return bottoms - np.array([0.0, length_px]), bottoms


def test_descriptor_distance_is_the_bhattacharyya_distance_of_the_histograms() -> None:
    a, b = _look(1), _look(2)
    roots, present = decode_descriptors([encode_descriptor(a), encode_descriptor(b), None, b"short"])
    assert present.tolist() == [True, True, False, False]
    distances = appearance_distances(roots[:2], roots[:2])
    exact = max(np.sqrt(1.0 - np.sum(np.sqrt(a[r] / a[r].sum() * b[r] / b[r].sum()))) for r in range(REGIONS))
    # float32 products: the coefficient of equal histograms is 1 within a few units of float32's last place, so
    # their distance, its square root's complement, is up to ~5e-4 (2.4e-4 on an AVX2 host, 0 on AVX-512 ones).
    assert abs(distances[0, 1] - exact) < 0.02 and distances[0, 0] < 1e-3
    disjoint = np.zeros((REGIONS, REGION_BINS))
    disjoint[:, 0], other = 1.0, np.zeros((REGIONS, REGION_BINS))
    other[:, 1] = 1.0
    roots, _ = decode_descriptors([encode_descriptor(disjoint), encode_descriptor(other)])
    assert appearance_distances(roots[:1], roots[1:])[0, 0] == 1.0


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), spacing_s=st.floats(1.5, 6.0), heading=st.floats(0.0, 2 * np.pi))
def test_a_walker_seen_every_few_seconds_is_one_individual(seed: int, spacing_s: float, heading: float) -> None:
    # 140 px for 1.32 m: a walk at 1.4 m/s is ~150 px/s sideways.
    times = np.arange(5) * spacing_s
    speed_px_s = 1.4 * 140 / 1.32
    tops, bottoms = _walker(times, (900, 700), (speed_px_s * np.cos(heading), 0.3 * speed_px_s * np.sin(heading)), 140)
    look = _look(seed)
    appearance = [_seen(look, seed + k) for k in range(5)]
    assert len(set(link_tracks(times, tops, bottoms))) == 5  # motion alone: gaps too long
    assert len(set(link_tracks(times, tops, bottoms, appearance=appearance))) == 1


def test_strangers_far_jumps_other_sizes_and_too_long_gaps_are_refused() -> None:
    times = np.array([0.0, 2.0])
    tops, bottoms = _walker(times, (900, 700), (100, 0), 140)
    look = _look(7)
    same = [_seen(look, 1), _seen(look, 2)]
    assert len(set(link_tracks(times, tops, bottoms, appearance=same))) == 1
    stranger = [_seen(look, 1), _seen(_look(8), 2)]
    roots, _ = decode_descriptors(stranger)
    assert appearance_distances(roots[:1], roots[1:])[0, 0] > MAX_APPEARANCE_DISTANCE
    assert len(set(link_tracks(times, tops, bottoms, appearance=stranger))) == 2
    # 1500 px in 2 s at 106 px/m is 7 m/s: not a walk.
    far = bottoms.copy()
    far[1, 0] += 1300
    assert len(set(link_tracks(times, far - (0, 140), far, appearance=same))) == 2
    # Half the size: another person (a child), or the same one 2 s later twice as far away: refused either way.
    small = tops.copy()
    small[1] = bottoms[1] - (0, 70)
    assert len(set(link_tracks(times, small, bottoms, appearance=same))) == 2
    late = np.array([0.0, LONG_MAX_GAP_S + 1.0])
    assert len(set(link_tracks(late, tops, bottoms, appearance=same))) == 2


def test_tracks_that_share_a_time_are_never_joined() -> None:
    # Two people dressed alike, walking side by side: a continuous track each at 5 fps; then only the left one is
    # seen again 3 s after both were last seen. Motion links each track; appearance joins the later sighting to
    # one of them, never the two tracks to each other.
    times = np.arange(5) * 0.2
    left = _walker(times, (700, 700), (100, 0), 140)
    right = _walker(times, (900, 700), (100, 0), 140)
    later = _walker(np.array([3.8]), (1080, 700), (0, 0), 140)
    look = _look(3)
    all_times = np.concatenate((times, times, [3.8]))
    tops = np.concatenate((left[0], right[0], later[0]))
    bottoms = np.concatenate((left[1], right[1], later[1]))
    appearance = [_seen(look, k) for k in range(11)]
    labels = link_tracks(all_times, tops, bottoms, appearance=appearance)
    assert len(set(labels[:5])) == 1 and len(set(labels[5:10])) == 1 and labels[0] != labels[5]
    assert len(set(labels)) == 2  # the later sighting joined one of them


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), people=st.integers(1, 12), frames=st.integers(1, 8), spacing_s=st.floats(0.04, 3.0))
def test_without_descriptors_the_labels_are_those_of_motion_alone(
    seed: int, people: int, frames: int, spacing_s: float
) -> None:
    rng = np.random.default_rng(seed)
    n = people * frames
    times, tops, bottoms = sightings(rng, people, frames, spacing_s)
    plain = link_tracks(times, tops, bottoms)
    assert np.array_equal(link_tracks(times, tops, bottoms, appearance=[None] * n), plain)
    # Descriptors of another layout (a shorter blob) count as none.
    assert np.array_equal(link_tracks(times, tops, bottoms, appearance=[b"\x01" * 8] * n), plain)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), people=st.integers(2, 10), frames=st.integers(2, 10), spacing_s=st.floats(0.2, 4.0))
def test_one_individual_is_never_seen_twice_in_one_frame(seed: int, people: int, frames: int, spacing_s: float) -> None:
    # A crowd dressed in three looks, standing about: appearance and reach admit many joins, but a label never
    # holds two observations of one frame time, whatever the long-gap stage joins.
    rng = np.random.default_rng(seed)
    n = people * frames
    times, tops, bottoms = sightings(rng, people, frames, spacing_s, crowd=True)
    looks = [_look(seed + k) for k in range(3)]
    appearance = [_seen(looks[rng.integers(3)], seed + i, noise=0.05) for i in range(n)]
    labels = link_tracks(times, tops, bottoms, appearance=appearance)
    for label in np.unique(labels):
        assert len(np.unique(times[labels == label])) == np.sum(labels == label)
