"""The COCO-17 reduction and the evidence rules of service.frames.keypoints (pure functions)."""

from __future__ import annotations

from dataclasses import replace

import pytest

from service.domain import PersonIn
from service.frames.keypoints import (
    MIN_SCORE,
    PARTIAL_REASON,
    coco_centres,
    drop_posted_repeats,
    evidence_problem,
    person_from_centres,
    person_from_keypoints,
)
from service.frames.measure import measure_people
from tests.render.scenes import calibration_of, tilted_scene
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


def test_a_posted_person_without_ankles_is_measured_as_partly_seen() -> None:
    """Shoulders without ankles: the client's pose did not see the lower body, standing or seated, so they are
    placed from their shoulders with the wide height sigma a person found in an image gets, not the standing one."""
    hidden = coco_person((500, 400), (510, 700))
    hidden[15] = [510.0, 700.0, 0.1]
    by_keypoints = person_from_keypoints(hidden, SIZE)
    by_centres = person_from_centres((500, 400), None, SIZE)
    assert by_keypoints.posture == by_centres.posture == "partial"
    assert person_from_keypoints(coco_person((500, 400), (510, 700)), SIZE).posture is None
    assert person_from_centres(None, (510, 700), SIZE).posture is None  # placed from the ankles: nothing to guess

    scene = tilted_scene(n_people=4)
    cal = calibration_of(scene)
    standing = PersonIn(tuple(scene.tops_px[0]), tuple(scene.bottoms_px[0]))  # type: ignore[arg-type]
    top = tuple(map(float, scene.tops_px[1]))
    posted = person_from_centres(top, None, SIZE)  # type: ignore[arg-type]
    found = PersonIn(top, None, unusable_reason=PARTIAL_REASON, posture="partial")  # type: ignore[arg-type]
    unsure = replace(posted, posture=None)
    pairs = [
        measure_people([standing, p], cal, distance_threshold_m=1.0).result.pairs[0] for p in (posted, found, unsure)
    ]
    assert pairs[0] == pairs[1] and pairs[0].distance_m == pairs[2].distance_m
    assert pairs[0].distance_std_m > 2 * pairs[2].distance_std_m


def test_a_body_posted_twice_is_kept_once() -> None:
    """Shoulder and ankle centres both within 5 % of the person's length of an earlier person's: the same body
    (two bodies cannot stand in one place); people a shoulder width apart, or seen only in part, are left alone."""
    people = [
        person_from_centres((500, 400), (510, 700), SIZE),
        person_from_centres((503, 402), (508, 712), SIZE),  # 3.6 and 12.2 px off a 300 px person: posted twice
        person_from_centres((540, 400), (550, 700), SIZE),  # 40 px (13 %) beside: another person
        person_from_centres((500, 400), None, SIZE),  # shoulders only: nothing to compare the ankles with
        person_from_centres((501, 401), (511, 701), SIZE),  # the first again: a repeat of person 0, not of 1
    ]
    kept = drop_posted_repeats(people)
    assert [p.shoulder_px is not None for p in kept] == [True, False, True, True, False]
    assert kept[1].unusable_reason == kept[4].unusable_reason == "same pose as person 0 (posted twice)"
    assert kept[1].ankle_px is None and kept[1].posture is None
    assert kept[0] == people[0] and kept[2] == people[2] and kept[3] == people[3]
    assert drop_posted_repeats(people[2:4]) == people[2:4]
