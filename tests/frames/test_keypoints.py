"""The COCO-17 reduction and the evidence rules of service.frames.keypoints (pure functions)."""

from __future__ import annotations

import pytest

from service.frames.keypoints import (
    MIN_SCORE,
    coco_centres,
    evidence_problem,
    person_from_centres,
    person_from_keypoints,
)
from tests.support.app import coco_person

SIZE = (1920, 1080)


def test_centres_are_midpoints_of_confident_pairs() -> None:
    points = coco_person((500, 400), (510, 700))
    assert coco_centres(points) == ((500, 400), (510, 700))
    points[15] = [points[15][0], points[15][1], MIN_SCORE - 0.01]  # one ankle unsure: no ankle centre
    assert coco_centres(points) == ((500, 400), None)
    points[5] = [points[5][0], points[5][1], 0.0]
    assert coco_centres(points) == (None, None)


def test_a_confident_upright_person_is_evidence() -> None:
    person = person_from_keypoints(coco_person((500, 400), (510, 700)), SIZE)
    assert person.unusable_reason is None
    assert person.shoulder_px == (500, 400) and person.ankle_px == (510, 700)
    assert person.keypoints is not None and len(person.keypoints) == 17


@pytest.mark.parametrize(
    ("shoulder", "ankle", "reason"),
    [
        (None, (500, 700), "shoulders"),
        ((500, 400), None, "ankles"),
        ((500, 400), (500, 1075), "border"),
        ((5, 400), (5, 700), "border"),
        ((500, 700), (500, 400), "not upright"),  # upside down
        ((500, 400), (900, 500), "not upright"),  # lying
        ((500, 400), (502, 405), "shorter"),
    ],
)
def test_evidence_rules(shoulder: tuple[float, float] | None, ankle: tuple[float, float] | None, reason: str) -> None:
    problem = evidence_problem(shoulder, ankle, SIZE)
    assert problem is not None and reason in problem


def test_perspective_tilt_is_tolerated() -> None:
    # 40 degrees from the image vertical: a standing person at the side of a wide-angle, rolled view.
    assert evidence_problem((500, 400), (752, 700), SIZE) is None
    assert person_from_centres((500, 400), None, SIZE).unusable_reason == "ankles not confidently seen"
