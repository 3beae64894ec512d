"""Possible repeats: the sigma of a sample whose walkers linking could not join (frames seconds apart).

link_tracks joins only what it can tell from a stranger, so sightings a second or more apart stay separate and
each counts as an independent height. `possible_repeats` groups every sighting the motion gates allow to be one
person across gaps of up to REPEAT_MAX_GAP_S; calibrate keeps the camera fitted to link_tracks' individuals and
evaluates its covariance with one height per group (the figures on 400 cameras are in `posemetry bench geometry
--only realistic`, row "frames 1 s apart")."""

from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.coverage import _times
from bench.simulate import SceneConfig, draw_scene
from service.geometry import CalibrationProblem, SolveOptions, calibrate
from service.geometry.tracks import REPEAT_MAX_SPAN_S, link_tracks, possible_repeats, united

from .test_tracks import _path, _seen


def _walk_seen(start_m: tuple[float, float], times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    points = _seen(_path(start_m, (1.2, 0.4), times_s))
    return points[:, 0], points[:, 1]


def test_a_walker_seen_every_two_seconds_is_one_possible_individual() -> None:
    times = np.arange(6) * 2.0
    tops, bottoms = _walk_seen((-4.0, 20.0), times)
    tracks = link_tracks(times, tops, bottoms)
    assert len(set(tracks)) == 6  # nothing links across 2 s without a velocity
    assert len(set(possible_repeats(times, tops, bottoms, tracks))) == 1
    # Two client ids are two people, however possible the link.
    ids = ["a"] * 3 + ["b"] * 3
    assert len(set(possible_repeats(times, tops, bottoms, tracks, client_tracks=ids))) == 2
    # Frames further apart than REPEAT_MAX_GAP_S say nothing.
    far = times * 4.0
    assert len(set(possible_repeats(far, tops, bottoms, link_tracks(far, tops, bottoms)))) == 6


def test_a_walk_longer_than_a_crossing_of_the_view_is_split() -> None:
    times = np.arange(0.0, 2.2 * REPEAT_MAX_SPAN_S, 2.0)
    tops, bottoms = _walk_seen((-20.0, 30.0), times * 0.02)  # one person standing nearly still for a minute
    groups = possible_repeats(times, tops, bottoms, np.arange(len(times)))
    assert 2 <= len(set(groups)) <= 4
    for label in set(groups):
        span = np.ptp(times[groups == label])
        assert span <= REPEAT_MAX_SPAN_S + 1e-9


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.integers(0, 5), min_size=1, max_size=30).flatmap(
        lambda a: st.tuples(st.just(a), st.lists(st.integers(0, 5), min_size=len(a), max_size=len(a)))
    )
)
def test_united_is_the_finest_grouping_coarser_than_both(pair: tuple[list[int], list[int]]) -> None:
    a, b = np.array(pair[0]), np.array(pair[1])
    groups = united(a, b)
    for labels in (a, b):  # coarser than each
        for label in set(labels.tolist()):
            assert len(set(groups[labels == label].tolist())) == 1
    # The finest such: every group is connected through shared labels of a or b.
    for group in set(groups.tolist()):
        members = set(np.flatnonzero(groups == group).tolist())
        reached, frontier = set(), {min(members)}
        while frontier:
            i = frontier.pop()
            reached.add(i)
            linked = set(np.flatnonzero((a == a[i]) | (b == b[i])).tolist())
            frontier |= linked - reached
        assert reached == members


def _sparse_scene(index: int):
    config = replace(SceneConfig.realistic(), walk_step_m=1.4)  # walkers seen 1 s apart
    return draw_scene(config, np.random.default_rng(np.random.SeedSequence(3, spawn_key=(zlib.crc32(b"x"), index))))


def test_the_camera_is_the_same_and_its_sigma_counts_the_individuals_it_could_be() -> None:
    """Measured on these six cameras: the normal's 1-sigma ellipse 1.15-1.45 times larger in area, the camera
    height's sigma 0-14 % larger; with the repeats equal to the individuals, nothing changes."""
    for index in range(6):
        scene = _sparse_scene(index)
        times = _times(scene, 1.0)
        tracks = link_tracks(times, scene.tops_px, scene.bottoms_px, height_m=1.32)
        repeats = possible_repeats(times, scene.tops_px, scene.bottoms_px, tracks, height_m=1.32)
        assert len(set(tracks)) == len(tracks) and len(set(repeats)) < 0.75 * len(tracks)
        problem = CalibrationProblem(scene.image_size, 1.32)
        plain = calibrate(scene.tops_px, scene.bottoms_px, problem, SolveOptions(seed=index), tracks=tracks)
        grouped = calibrate(
            scene.tops_px, scene.bottoms_px, problem, SolveOptions(seed=index), tracks=tracks, repeats=repeats
        )
        same = calibrate(
            scene.tops_px, scene.bottoms_px, problem, SolveOptions(seed=index), tracks=tracks, repeats=tracks
        )
        assert (grouped.fx, grouped.rho, grouped.individuals) == (plain.fx, plain.rho, plain.individuals)
        assert np.array_equal(grouped.normal, plain.normal)
        assert np.array_equal(same.uncertainty.covariance, plain.uncertainty.covariance)
        area = [np.linalg.det(cal.uncertainty.covariance[2:4, 2:4]) ** 0.5 for cal in (plain, grouped)]
        assert area[1] >= 1.1 * area[0]
        assert grouped.uncertainty.rho_m >= plain.uncertainty.rho_m
