"""The appearance descriptor: torso and legs from the keypoints, people in front left out, and on real frames one
walker's descriptors alike across frames while strangers' differ."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from service.geometry.appearance import APPEARANCE_BINS, appearance_distances, decode_descriptors
from service.pose.appearance import appearance_descriptor
from service.pose.pipeline import TopDownPose
from tests.pose.conftest import POSE

RED, BLUE, GREEN, GREY = (0, 0, 200), (200, 0, 0), (0, 200, 0), (128, 128, 128)


def _painted() -> np.ndarray:
    """POSE's person painted on grey: a red top (shoulders to hips) and blue trousers (hips to ankles)."""
    image = np.full((700, 1000, 3), GREY, dtype=np.uint8)
    image[330:432, 465:536] = RED
    image[428:512, 470:530] = BLUE
    return image


def _hue_bin(bgr: tuple[int, int, int]) -> int:
    hue = int(cv2.cvtColor(np.array([[bgr]], dtype=np.uint8), cv2.COLOR_BGR2HSV)[0, 0, 0])
    return hue * APPEARANCE_BINS[0] // 180


def test_torso_and_legs_are_read_from_their_own_pixels() -> None:
    scores, box = np.ones(17), np.array([460.0, 290.0, 540.0, 515.0])
    descriptor = appearance_descriptor(_painted(), POSE, scores, box, np.zeros((0, 4)))
    assert descriptor is not None
    roots, present = decode_descriptors([descriptor])
    hist = (roots[0] ** 2).reshape(2, *APPEARANCE_BINS).sum(axis=(2, 3))  # per region, mass per hue bin
    assert present[0] and hist[0, _hue_bin(RED)] > 0.9 and hist[1, _hue_bin(BLUE)] > 0.9
    # Without hips (not seen) there is no torso: no descriptor.
    hidden = scores.copy()
    hidden[[11, 12]] = 0.1
    assert appearance_descriptor(_painted(), POSE, hidden, box, np.zeros((0, 4))) is None


def test_pixels_inside_a_person_in_front_are_left_out() -> None:
    scores, box = np.ones(17), np.array([460.0, 290.0, 540.0, 515.0])
    clean = appearance_descriptor(_painted(), POSE, scores, box, np.zeros((0, 4)))
    covered = _painted()
    covered[380:520, 440:500] = GREEN  # someone nearer in a green coat covers the left half of the body
    front = np.array([[440.0, 380.0, 500.0, 560.0]])
    seen = appearance_descriptor(covered, POSE, scores, box, np.zeros((0, 4)))
    masked = appearance_descriptor(covered, POSE, scores, box, front)
    assert clean is not None and seen is not None and masked is not None
    roots, _ = decode_descriptors([clean, seen, masked])
    distances = appearance_distances(roots, roots)
    assert distances[0, 1] > 0.5 and distances[0, 2] < 0.05


def test_walkers_look_alike_across_frames_on_town_centre(
    thunder: TopDownPose, town_frames: dict[int, np.ndarray]
) -> None:
    # Frames 0 and 30 (1.2 s apart): the standing people carry descriptors. Matched one-to-one by distance, the
    # pairs under 0.4 (one person's median is 0.26 on the clip, strangers' 0.89) are plausible walks (under 2 m/s at
    # ~130 px per metre: 310 px), and most pairs are strangers, far apart. Measured: 0.14, 0.31, 0.32, 0.36 and
    # four pairs over 0.68; median of all pairs 0.92.
    people = {number: thunder(town_frames[number]) for number in (0, 30)}
    for found in people.values():
        assert sum(person.appearance is not None for person in found) >= 4
        assert all(person.appearance is None for person in found if person.posture != "standing")
    first, second = ([p for p in people[n] if p.appearance is not None] for n in (0, 30))
    roots_a, _ = decode_descriptors([p.appearance for p in first])
    roots_b, _ = decode_descriptors([p.appearance for p in second])
    distances = appearance_distances(roots_a, roots_b)
    rows, cols = linear_sum_assignment(distances)
    alike = [(r, c) for r, c in zip(rows, cols, strict=True) if distances[r, c] < 0.4]
    assert len(alike) >= 3
    for r, c in alike:
        ankles_a = first[r].keypoints_px[[15, 16]].mean(axis=0)
        ankles_b = second[c].keypoints_px[[15, 16]].mean(axis=0)
        assert np.hypot(*(ankles_b - ankles_a)) < 310
    assert np.median(distances) > 0.6
