"""People the pose cannot read are placed from their detector box's bottom (service.frames.keypoints.place_from_boxes)
where it is a ground contact, with the cue's wider sigma, and are never calibration evidence."""

from __future__ import annotations

from dataclasses import replace

import pytest

from service.domain import PersonIn
from service.frames.keypoints import (
    BOX_ANKLE_OFFSET,
    BOX_REASON,
    PARTIAL_REASON,
    STATIC_REASON,
    as_static,
    box_bottom_problem,
    place_from_boxes,
)
from service.frames.measure import measure_people
from tests.render.scenes import calibration_of, tilted_scene

IMAGE_SIZE = (1920, 1080)
THRESHOLD_M = 1.8288
BOX = (900.0, 400.0, 980.0, 640.0)


def _unread(box_px: tuple[float, float, float, float], score: float) -> PersonIn:
    """A detected person whose pose was not read: only the detector's box and score."""
    return PersonIn(
        shoulder_px=None,
        ankle_px=None,
        unusable_reason="shoulders not confidently seen",
        box_px=box_px,
        detection_score=score,
    )


def test_a_box_whose_bottom_is_clear_is_a_contact() -> None:
    assert box_bottom_problem(BOX, [(1100.0, 380.0, 1180.0, 620.0)], IMAGE_SIZE) is None


@pytest.mark.parametrize(
    ("box", "others", "problem"),
    [
        ((900.0, 700.0, 980.0, 1079.0), [], "box cut by the image border"),  # legs below the frame
        ((2.0, 400.0, 80.0, 640.0), [], "box cut by the image border"),  # half outside on the left
        ((900.0, 0.0, 950.0, 100.0), [], "box cut by the image border"),  # head out of view: a person, or a bicycle?
        # Behind someone whose box reaches lower: the box ends where the person disappears, not at their feet.
        (BOX, [(880.0, 450.0, 990.0, 760.0)], "box bottom inside another person's box"),
        # A second box of one person (their legs boxed apart), its bottom on the other's bottom edge.
        ((910.0, 520.0, 970.0, 640.0), [BOX], "box mostly inside another person's box"),
        # Behind someone whose box begins lower and ends level with it (Town Centre frame 36: the woman behind the
        # woman in red, boxed down to hidden feet, its bottom centre just right of the other's box).
        (
            (1722.0, 677.0, 1812.0, 996.0),
            [(1634.0, 741.0, 1757.0, 998.0)],
            "box ends level with the box of a person in front of it (drawn down to hidden feet)",
        ),
    ],
)
def test_a_box_cut_by_the_frame_or_by_another_person_is_no_contact(
    box: tuple[float, float, float, float], others: list[tuple[float, float, float, float]], problem: str
) -> None:
    assert box_bottom_problem(box, others, IMAGE_SIZE) == problem


def test_only_a_box_the_detector_believes_stands_in_front() -> None:
    """A suitcase boxed at 0.44 beside its owner's legs (Town Centre frame 60) does not unplace him."""
    owner = _unread((1793.0, 377.0, 1868.0, 610.0), 0.83)
    suitcase = _unread((1782.0, 448.0, 1824.0, 604.0), 0.44)
    assert box_bottom_problem(owner.box_px, [suitcase.box_px], IMAGE_SIZE) is not None  # type: ignore[arg-type]
    placed = place_from_boxes([owner, suitcase], IMAGE_SIZE)
    assert placed[0].unusable_reason == BOX_REASON and placed[0].placed_from_box and placed[0].ankle_px is not None
    confident = place_from_boxes([owner, replace(suitcase, detection_score=0.6)], IMAGE_SIZE)
    assert confident[0].ankle_px is None


def test_unread_people_with_a_clear_box_are_placed_from_it_and_are_never_evidence() -> None:
    unread = _unread(BOX, 0.8)
    hidden = PARTIAL_REASON
    behind = PersonIn(
        shoulder_px=(1130.0, 420.0),
        ankle_px=None,
        unusable_reason=hidden,
        box_px=(1100.0, 380.0, 1160.0, 600.0),
        detection_score=0.8,
    )
    in_front = PersonIn(
        shoulder_px=(1135.0, 480.0),
        ankle_px=(1135.0, 700.0),
        box_px=(1090.0, 440.0, 1180.0, 720.0),
        detection_score=0.9,
    )
    # Shoulders low in the box: the box ends at a wall or a table, not at the feet.
    walled = replace(behind, shoulder_px=(1500.0, 520.0), box_px=(1470.0, 480.0, 1530.0, 600.0))
    repeat = PersonIn(
        shoulder_px=None,
        ankle_px=None,
        unusable_reason="same pose as person 2",
        box_px=(300.0, 300.0, 360.0, 500.0),
        detection_score=0.8,
    )
    assert place_from_boxes([repeat], IMAGE_SIZE)[0].placed_from_box  # a clear box, unless known to be a repeat
    # A box the detector doubts (score 0.4): on Town Centre such boxes are rarely pedestrians.
    doubtful = replace(unread, box_px=(1300.0, 400.0, 1380.0, 640.0), detection_score=0.4)
    placed = place_from_boxes([unread, behind, in_front, walled, repeat, doubtful], IMAGE_SIZE, repeats={4})
    contact = (940.0, 640.0 - BOX_ANKLE_OFFSET * 240.0)
    assert placed[0].ankle_px == pytest.approx(contact) and placed[0].unusable_reason == BOX_REASON
    assert [person.placed_from_box for person in placed] == [True] + [False] * 5
    assert placed[1] == behind  # its box bottom lies inside the box of the person in front: shoulders only
    assert placed[2] == in_front  # trusted ankles are kept
    assert placed[3] == walled and placed[4] == repeat and placed[5] == doubtful
    assert all(person.unusable_reason is not None for person in placed[:2] + placed[3:])


def test_a_box_placed_person_counts_in_violations_with_a_wider_sigma() -> None:
    scene = tilted_scene(n_people=6)
    cal = calibration_of(scene)
    ankles = [tuple(map(float, b)) for b in scene.bottoms_px[:3]]
    tops = [tuple(map(float, t)) for t in scene.tops_px[:3]]
    by_ankles = [PersonIn(shoulder_px=t, ankle_px=a) for t, a in zip(tops, ankles, strict=True)]  # type: ignore[arg-type]
    by_box = [
        by_ankles[0],
        *(PersonIn(shoulder_px=None, ankle_px=a, unusable_reason=BOX_REASON, placed_from_box=True) for a in ankles[1:]),  # type: ignore[arg-type]
    ]
    exact = measure_people(by_ankles, cal, distance_threshold_m=100.0, noise_px=1.0).result
    boxed = measure_people(by_box, cal, distance_threshold_m=100.0, noise_px=1.0).result
    assert [p.placed_from for p in boxed.people] == ["ankles", "box", "box"]
    for a, b in zip(exact.pairs, boxed.pairs, strict=True):
        assert b.distance_m == pytest.approx(a.distance_m)  # same points: placed where the contact puts them
        assert b.distance_std_m > 2 * a.distance_std_m  # with the cue's sigma, on both people of a pair
    assert len(boxed.violations) == 3  # and they take part in violations


def test_a_static_box_placed_person_keeps_the_box_placement_and_raises_no_violation() -> None:
    scene = tilted_scene(n_people=6)
    cal = calibration_of(scene)
    a, b = (tuple(map(float, p)) for p in scene.bottoms_px[:2])
    people = [
        PersonIn(shoulder_px=None, ankle_px=a),
        PersonIn(shoulder_px=None, ankle_px=b, unusable_reason=BOX_REASON, placed_from_box=True),
    ]  # type: ignore[arg-type]
    people[1] = as_static(people[1])
    assert people[1].unusable_reason == STATIC_REASON and people[1].static and people[1].placed_from_box
    result = measure_people(people, cal, distance_threshold_m=100.0).result
    assert [p.placed_from for p in result.people] == ["ankles", "box"] and result.people[1].static
    assert result.violations == []
