"""Two detections with one pose are one person: the copy is kept as a detection but neither placed nor evidence."""

from __future__ import annotations

import numpy as np

from service.frames.keypoints import people_from_detections
from service.pose.pipeline import TopDownPose
from service.pose.types import DetectedPerson

from .conftest import IMAGE_SIZE, POSE


def _person(keypoints: np.ndarray, box: tuple[float, float, float, float], score: float) -> DetectedPerson:
    return DetectedPerson(box, score, keypoints, np.full(17, 0.8))


def test_a_repeated_pose_is_dropped_and_a_close_neighbour_kept() -> None:
    rng = np.random.default_rng(0)
    found = [
        _person(POSE, (460, 290, 540, 515), 0.8),
        # The same person read again from a neighbour's box (a few px of crop-to-crop jitter).
        _person(POSE + rng.normal(0, 1.5, POSE.shape), (390, 280, 455, 500), 0.6),
        # Someone pressed against them: a shoulder width (~50 px) to the right.
        _person(POSE + (50.0, 4.0), (505, 292, 590, 518), 0.5),
    ]
    people = people_from_detections(found, (1920, 1080))
    assert people[0].unusable_reason is None and people[2].unusable_reason is None
    assert people[1].shoulder_px is None and people[1].ankle_px is None
    assert people[1].unusable_reason is not None and "same pose as person 0" in people[1].unusable_reason
    assert people[1].box_px == (390, 280, 455, 500) and people[1].keypoints is not None  # the detection stays


def test_no_two_people_of_a_real_frame_share_a_pose(thunder: TopDownPose, town_frames: dict[int, np.ndarray]) -> None:
    """Town Centre frame 0 has such copies (a person read in a neighbour's crop); none survive as placed people."""
    people = people_from_detections(thunder(town_frames[0]), IMAGE_SIZE)
    copies = [p for p in people if p.unusable_reason is not None and p.unusable_reason.startswith("same pose")]
    assert 1 <= len(copies) <= len(people) // 3
    placed = [p for p in people if p.shoulder_px is not None]
    for a in range(len(placed)):
        for b in range(a + 1, len(placed)):
            gap_px = np.hypot(*np.subtract(placed[a].shoulder_px, placed[b].shoulder_px))
            height_px = max(p.box_px[3] - p.box_px[1] for p in (placed[a], placed[b]))  # type: ignore[index]
            assert gap_px > 0.05 * height_px


def test_two_boxes_placing_one_person_at_one_point_are_one_person() -> None:
    """A person cut by the frame's bottom edge, boxed twice: only the head and shoulders are seen in each box, and
    the arms disagree, but both would be placed from the same shoulder centre: a 0.01 m "violation" otherwise."""
    upper = POSE.copy()
    other = POSE + np.random.default_rng(1).normal(0, 25, POSE.shape)  # arms and legs read differently
    other[5:7] = upper[5:7] + 0.5  # the shoulders agree
    scores = np.full(17, 0.8)
    scores[11:] = 0.1  # hips, knees and ankles out of view
    found = [
        DetectedPerson((460, 290, 540, 515), 0.8, upper, scores),
        DetectedPerson((440, 292, 520, 515), 0.4, other, scores),
    ]
    people = people_from_detections(found, (1920, 1080))
    assert people[0].shoulder_px is not None and people[1].shoulder_px is None
    assert "same pose as person 0" in (people[1].unusable_reason or "")
