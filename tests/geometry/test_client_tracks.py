"""Client track ids in linking: one id is one individual across gaps of up to a minute, two ids never one, no id
changes nothing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.geometry import CalibrationProblem
from service.geometry.appearance import APPEARANCE_REGIONS, REGION_BINS, encode_descriptor
from service.geometry.evidence import solve_evidence
from service.geometry.tracks import CLIENT_MAX_GAP_S, MAX_GAP_S, link_tracks
from tests.support.geometry import sightings


def _walker(times_s: np.ndarray, start_px: tuple[float, float], step_px_s: tuple[float, float], length_px: float):
    bottoms = np.array(start_px) + times_s[:, None] * np.array(step_px_s)
    return bottoms - np.array([0.0, length_px]), bottoms


def _look(seed: int, sightings: int) -> list[bytes]:
    """One person's descriptors over several sightings: alike enough for the long-gap stage to join them."""
    rng = np.random.default_rng(seed)
    look = rng.dirichlet(np.full(REGION_BINS, 0.05), size=len(APPEARANCE_REGIONS))
    return [encode_descriptor(look * rng.uniform(0.95, 1.05, size=look.shape) + 1e-4) for _ in range(sightings)]


def test_one_id_is_one_individual_across_a_ten_second_gap() -> None:
    # Two walkers seen at 0 s and again at 10 s, each 1.5 m further on: far beyond any motion gate.
    times = np.array([0.0, 0.0, 10.0, 10.0])
    tops, bottoms = _walker(times, (500, 700), (15, 0), 140)
    tops[1::2] += (700, -50)
    bottoms[1::2] += (700, -50)
    assert len(set(link_tracks(times, tops, bottoms))) == 4
    labels = link_tracks(times, tops, bottoms, client_tracks=["a", "b", "a", "b"])
    assert labels[0] == labels[2] and labels[1] == labels[3] and labels[0] != labels[1]
    assert sorted(set(labels.tolist())) == [0, 1]


def test_an_id_seen_again_after_more_than_a_minute_is_another_individual() -> None:
    """A tracker that restarts numbers its people from 1 again: "7" at 0-4 s and "7" 90 s later are two people
    (merging them would force two heights into one); within a minute of each other they are one."""
    times = np.array([0.0, 2.0, 4.0, 94.0, 96.0, 96.0 + CLIENT_MAX_GAP_S])
    tops, bottoms = _walker(times, (500, 700), (1, 0), 140)
    labels = link_tracks(times, tops, bottoms, client_tracks=["7"] * len(times))
    assert len(set(labels[:3])) == 1 and len(set(labels[3:])) == 1 and labels[0] != labels[3]
    # In any order, and with a sighting placed later than a minute's steps: only the gap between sightings counts.
    order = np.array([5, 3, 0, 4, 2, 1])
    shuffled = link_tracks(times[order], tops[order], bottoms[order], client_tracks=["7"] * 6)
    back = shuffled[np.argsort(order)]  # each observation's label, in the original order
    assert (back == back[0]).tolist() == [True] * 3 + [False] * 3 and len(set(back[3:])) == 1


def test_two_ids_are_never_one_individual_whatever_motion_says() -> None:
    # A walker at 25 fps, whom motion links into one track; the client says the first half and the second half
    # are two people (a swap the tracker saw and the gates cannot).
    times = np.arange(20) / 25.0
    tops, bottoms = _walker(times, (500, 700), (100, 0), 140)
    assert len(set(link_tracks(times, tops, bottoms))) == 1
    ids = ["a"] * 10 + ["b"] * 10
    labels = link_tracks(times, tops, bottoms, client_tracks=ids)
    assert len(set(labels[:10])) == 1 and len(set(labels[10:])) == 1 and labels[0] != labels[10]
    # Sightings without an id between them still link by motion, to the id before them; the next id stays apart.
    gaps: list[str | None] = ["a"] * 5 + [None] * 10 + ["b"] * 5
    labels = link_tracks(times, tops, bottoms, client_tracks=gaps)
    assert len(set(labels[:15])) == 1 and len(set(labels[15:])) == 1 and labels[0] != labels[15]


def test_two_ids_are_never_one_individual_whatever_appearance_says() -> None:
    # One look seen every 3 s: the long-gap stage joins all five sightings; with ids it joins only within an id,
    # through sightings without one, and never across ids.
    times = np.arange(5) * 3.0
    assert times[1] > MAX_GAP_S
    tops, bottoms = _walker(times, (500, 700), (100, 0), 140)
    looks = _look(5, 5)
    assert len(set(link_tracks(times, tops, bottoms, appearance=looks))) == 1
    labels = link_tracks(times, tops, bottoms, appearance=looks, client_tracks=["a", None, "b", None, "a"])
    assert labels[0] == labels[1] == labels[4] and labels[0] != labels[2]
    assert len(set(labels.tolist())) == 2  # the sighting at 9 s joins one of the ids' chains, never both


def test_ids_unite_what_linking_left_apart_and_keep_unlinked_strangers_apart() -> None:
    # Four sightings of one id 2 s apart (a 0.5 fps keypoint stream) and two strangers without ids.
    times = np.array([0.0, 2.0, 4.0, 6.0, 2.0, 4.0])
    tops, bottoms = _walker(times, (300, 700), (150, 0), 140)
    tops[4:] += (0, -300)
    bottoms[4:] += (0, -300)
    labels = link_tracks(times, tops, bottoms, client_tracks=["17"] * 4 + [None, None])
    assert len(set(labels[:4])) == 1 and len(set(labels)) == 3


def test_ids_must_be_one_per_observation() -> None:
    times, (tops, bottoms) = np.zeros(2), _walker(np.zeros(2), (500, 700), (0, 0), 140)
    with pytest.raises(ValueError, match="one id"):
        link_tracks(times, tops, bottoms, client_tracks=["a"])
    problem = CalibrationProblem((1920, 1080), 1.32)
    with pytest.raises(ValueError, match="times_s"):
        solve_evidence(tops, bottoms, problem, client_tracks=["a", "b"])


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    people=st.integers(1, 10),
    frames=st.integers(1, 8),
    spacing_s=st.floats(0.04, 3.0),
    described=st.booleans(),
)
def test_without_ids_the_labels_are_those_of_linking_without_them(
    seed: int, people: int, frames: int, spacing_s: float, described: bool
) -> None:
    rng = np.random.default_rng(seed)
    n = people * frames
    times, tops, bottoms = sightings(rng, people, frames, spacing_s)
    appearance = [look for k in range(people) for look in _look(seed + k, frames)] if described else None
    plain = link_tracks(times, tops, bottoms, appearance=appearance)
    assert np.array_equal(link_tracks(times, tops, bottoms, appearance=appearance, client_tracks=[None] * n), plain)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), people=st.integers(2, 8), frames=st.integers(2, 8), spacing_s=st.floats(0.04, 3.0))
def test_each_id_is_exactly_one_label(seed: int, people: int, frames: int, spacing_s: float) -> None:
    # People standing about in a small area (motion and appearance would link many of them), each with an id on
    # some sightings: a label holds one id, and every id's sightings share one label.
    rng = np.random.default_rng(seed)
    n = people * frames
    times, tops, bottoms = sightings(rng, people, frames, spacing_s, crowd=True)
    appearance = [look for look in _look(seed, n)]
    ids = [None if rng.random() < 0.3 else f"p{rng.integers(people)}" for _ in range(n)]
    labels = link_tracks(times, tops, bottoms, appearance=appearance, client_tracks=ids)
    for track in {i for i in ids if i is not None}:
        assert len({labels[k] for k in range(n) if ids[k] == track}) == 1
    for label in np.unique(labels):
        assert len({ids[k] for k in np.flatnonzero(labels == label)} - {None}) <= 1
    assert sorted(set(labels.tolist())) == list(range(len(set(labels.tolist()))))
