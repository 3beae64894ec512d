"""From posted people to the two points the geometry uses, and whether a person is calibration evidence (pure).

The geometry needs, per person, the shoulder centre (top) and the ankle centre (bottom). Measuring a frame
only needs one of them; calibrating needs both, from people who stand upright and are fully in view, because
every calibration assumes the shoulder centre lies `person_height_m` straight above the ankle centre. The rules
below therefore keep points for measurement generously and admit evidence conservatively:

- Confidence: a centre exists only when *both* of its keypoints score at least `MIN_SCORE` (0.3, the usual
  pose-model visibility cut-off). Averaging one confident and one guessed ankle moves the centre by up to half a
  stride, which is worse than not having it.
- Border: a person with either centre within `BORDER_FRACTION` (1%) of an image side is likely cut off by the
  frame (the pose model then guesses the hidden joints at the edge), so they are not evidence.
- Upright: the ankle centre must be below the shoulder centre in the image, and the shoulder-to-ankle segment
  within `MAX_TILT_DEG` (60 degrees) of the image vertical. Perspective and camera roll tilt standing people
  away from the image vertical (towards the vertical vanishing point), so a tight cut would reject real
  evidence at the image sides; the rule only removes people who are plainly lying, falling or mis-detected.
  Subtler cases (sitting, bending) are left to the calibration's RANSAC and misfit rejection, which handle them
  against the whole evidence, something a per-person rule without a camera model cannot do.
- Size: a segment shorter than `MIN_SEGMENT_PX` (8 px) carries more keypoint noise than direction.

Centres posted explicitly (`shoulder`/`ankle`) have no scores; the border, upright and size rules still apply.

People found in an image come with the pose pipeline's own verdict (service/pose/assess.py), which sees the whole
frame: which keypoints are trustworthy (seen, not inside the box of a person in front, an ankle only below a seen
knee) and the posture. `person_from_detection` builds centres from trusted keypoints only, so an ankle guessed
behind someone else never places a person (they are placed from their shoulders, or not at all), and only
`standing` people can be evidence: `seated` ones (legs seen but folded) and `partial` ones (lower body not seen)
are measured, never calibrated on. The store keeps the posture (`PersonIn.posture`), which measuring reads; the
reasons (`SEATED_REASON`, `PARTIAL_REASON`, ...) say the same in words.

One rule needs the whole frame: a top-down pipeline runs the pose model on each detection's crop, and two
detections can yield the same pose, either because the detector boxed one person twice (a whole-body and a
partial box) or because a crop around one person also holds a more salient neighbour and the single-person pose
model reads the neighbour. The second pose is then a copy of the first: measured, it is a phantom person a few
centimetres from the real one (a false violation in every such frame; seen on the Oxford Town Centre clip in
most frames). `people_from_detections` therefore drops the points of a pose that repeats a more confident
detection's pose (median distance between their keypoints under `DUPLICATE_POSE_FRACTION` of the box height, or
the shoulder or ankle centre that would place them that close to the other's: two boxes of a person cut by the
frame's edge agree on little but their shoulders): the detection is kept, with the reason, but is neither
evidence nor placed.

A person the pose cannot put on the ground (no trusted ankles) still counts in distances and violations, so
`people_from_detections` then places them from their detector box's bottom where it is a ground contact
(`place_from_boxes`, `box_bottom_problem`): measured, with a wider sigma, never calibration evidence.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from service.domain import PersonIn, Posture
from service.pose.occlusion import drawn_to_feet_in_front

if TYPE_CHECKING:
    from service.pose.types import DetectedPerson

# COCO-17 order: nose, eyes (1, 2), ears (3, 4), shoulders (5, 6), elbows, wrists, hips (11, 12), knees, ankles.
LEFT_SHOULDER, RIGHT_SHOULDER = 5, 6
LEFT_ANKLE, RIGHT_ANKLE = 15, 16
MIN_SCORE = 0.3
BORDER_FRACTION = 0.01
MAX_TILT_DEG = 60.0
MIN_SEGMENT_PX = 8.0
# Two poses in one frame are the same person when their keypoints lie this close (median over the keypoints
# confident in both, as a fraction of the taller box). The same person read from two crops differs by a few
# pixels (~1-2 % of their height); two people pressed together differ by a shoulder width (~25 %).
DUPLICATE_POSE_FRACTION = 0.05
MIN_SHARED_KEYPOINTS = 4
# Box-bottom placement (`place_from_boxes`): the share of a box inside another that makes it a second box of one
# person.
BOX_INSIDE_FRACTION = 0.8
# How far above the box bottom the ankle centre lies, as a fraction of the box height (Town Centre, measured on
# the people placed from trusted ankles: docs/benchmarks/pose.md).
BOX_ANKLE_OFFSET = 0.10
# Where the shoulders are seen, a box that is a whole person holds them in its top part: shoulder centre to box
# bottom at least this fraction of the box height (0.81 median, 0.78 at the 5th percentile, 0.75 at the 1st for the
# people with trusted ankles on Town Centre; a box cut at the hips by a wall or a table: ~0.5; frame 54's woman in
# red, legs hidden by the low wall and the frame's edge: 0.72-0.76 by detector pass). A whole person below it is
# still placed, from their shoulders.
BOX_MIN_SHOULDER_DROP = 0.78
# Without trusted shoulders a box is only as good as the detector's belief that it holds a person: on Town Centre,
# of such whole box-placed detections under this score 10 % match an annotated pedestrian (68 of them; 83 % at or
# above it; with trusted shoulders 62 % under it, 96 % above).
BOX_MIN_SCORE = 0.5
SEATED_REASON = "seated or crouching (legs seen but folded): a position, not calibration evidence"
PARTIAL_REASON = "lower body not seen (hidden or out of view): placed from the shoulders, not calibration evidence"
BOX_REASON = "pose not read: placed from the detector box's bottom (a clear ground contact), a position, not evidence"
STATIC_REASON = "static: found at a spot where nothing has moved for a long time (a mannequin, a poster, a statue)"

Point = tuple[float, float]


def _centre(keypoints: Sequence[Sequence[float]], a: int, b: int, min_score: float) -> Point | None:
    """Midpoint of two keypoints, or None unless both are confident."""
    ka, kb = keypoints[a], keypoints[b]
    if ka[2] < min_score or kb[2] < min_score:
        return None
    return ((ka[0] + kb[0]) / 2.0, (ka[1] + kb[1]) / 2.0)


def coco_centres(
    keypoints: Sequence[Sequence[float]], *, min_score: float = MIN_SCORE
) -> tuple[Point | None, Point | None]:
    """(shoulder centre, ankle centre) of one COCO-17 person; None for a centre whose keypoints are not confident."""
    shoulder = _centre(keypoints, LEFT_SHOULDER, RIGHT_SHOULDER, min_score)
    ankle = _centre(keypoints, LEFT_ANKLE, RIGHT_ANKLE, min_score)
    return shoulder, ankle


def evidence_problem(shoulder: Point | None, ankle: Point | None, image_size_px: tuple[int, int]) -> str | None:
    """Why a person is not usable as calibration evidence, or None when they are (see the module docstring)."""
    if shoulder is None:
        return "shoulders not confidently seen"
    if ankle is None:
        return "ankles not confidently seen"
    width_px, height_px = image_size_px
    margin_x_px, margin_y_px = BORDER_FRACTION * width_px, BORDER_FRACTION * height_px
    for x, y in (shoulder, ankle):
        if x < margin_x_px or x > width_px - margin_x_px or y < margin_y_px or y > height_px - margin_y_px:
            return "touching the image border"
    dx_px, dy_px = ankle[0] - shoulder[0], ankle[1] - shoulder[1]
    if math.hypot(dx_px, dy_px) < MIN_SEGMENT_PX:
        return f"shoulder-to-ankle segment shorter than {MIN_SEGMENT_PX:g} px"
    if dy_px <= 0 or math.degrees(math.atan2(abs(dx_px), dy_px)) > MAX_TILT_DEG:
        return f"not upright (ankles not below shoulders within {MAX_TILT_DEG:g} degrees)"
    return None


def person_from_keypoints(
    keypoints: Sequence[Sequence[float]],
    image_size_px: tuple[int, int],
    *,
    min_score: float = MIN_SCORE,
    track_id: str | None = None,
) -> PersonIn:
    """A COCO-17 person as the store's row: centres, raw keypoints (kept for re-analysis), the verdict and the
    client's track id, if it gave one."""
    shoulder, ankle = coco_centres(keypoints, min_score=min_score)
    return PersonIn(
        shoulder_px=shoulder,
        ankle_px=ankle,
        keypoints=keypoints,
        unusable_reason=evidence_problem(shoulder, ankle, image_size_px),
        track_id=track_id,
        posture=_posted_posture(shoulder, ankle),
    )


def _posted_posture(shoulder: Point | None, ankle: Point | None) -> Posture | None:
    """What a posted person's points say of their posture: `partial` when the shoulders came without the ankles
    (the client's pose did not see the lower body, so nobody can tell standing from seated: measured with the
    wide height sigma, as such a person found in an image is), else nothing."""
    return "partial" if shoulder is not None and ankle is None else None


def person_from_detection(person: DetectedPerson, image_size_px: tuple[int, int]) -> PersonIn:
    """A person the pose model found, as the store's row: centres from trusted keypoints, the posture's verdict,
    the raw keypoints (kept for re-analysis), the detector's box and score, and the appearance descriptor."""
    keypoints = person.coco_keypoints()
    row = person_from_keypoints(keypoints, image_size_px)
    if person.keypoint_trusted is not None:
        trusted = [
            [x, y, score if ok else 0.0] for (x, y, score), ok in zip(keypoints, person.keypoint_trusted, strict=True)
        ]
        shoulder, ankle = coco_centres(trusted)
        reason = evidence_problem(shoulder, ankle, image_size_px)
        if person.posture == "seated":
            reason = SEATED_REASON
        elif person.posture == "partial":
            reason = PARTIAL_REASON
        row = replace(row, shoulder_px=shoulder, ankle_px=ankle, unusable_reason=reason, posture=person.posture)
    return replace(
        row,
        box_px=tuple(float(v) for v in person.box_xyxy_px),
        detection_score=person.detection_score,
        appearance=person.appearance,
    )


def box_bottom_problem(
    box_px: Sequence[float],
    others_px: Sequence[Sequence[float]],
    image_size_px: tuple[int, int],
    front_px: Sequence[Sequence[float]] | None = None,
) -> str | None:
    """Why a detector box's bottom centre is not a ground contact, or None when it is (see `place_from_boxes`).

    Not a contact: a box cut by the frame (the detector boxes what is in view: at the bottom edge the feet are
    out of view, at a side the centre moves, and at the top nothing says the box holds a person rather than the
    bicycle beside one, as on Town Centre frame 88), a bottom centre inside another person's box (the box of a
    person behind someone ends where they disappear, not at their feet; unlike a keypoint, the whole box is an
    occluder here: a contact that might be a guess places nobody), a box mostly inside another one (a second
    box of one person), or a box ending level with the box of a person in front of it (service/pose/occlusion.py,
    `drawn_to_feet_in_front`: their box begins lower, covers a fifth of this one and ends within 5 % of its height
    of this one's bottom): someone further away has their feet higher in the image than the person in front, so
    such a box was drawn down to hidden feet (Town Centre frame 36: the woman behind the woman in red, boxed to
    the other's feet, 0.45 m from her).
    `front_px`: the boxes that can be such a person in front (default: all of `others_px`); `place_from_boxes`
    passes those the detector believes (`BOX_MIN_SCORE`), so that a suitcase boxed at 0.44 beside its owner's
    legs does not unplace him (Town Centre frame 60).
    """
    left, top, right, bottom = (float(v) for v in box_px)
    width_px, height_px = image_size_px
    margin_x_px, margin_y_px = BORDER_FRACTION * width_px, BORDER_FRACTION * height_px
    if (
        top <= margin_y_px
        or bottom >= height_px - margin_y_px
        or left <= margin_x_px
        or right >= width_px - margin_x_px
    ):
        return "box cut by the image border"
    x_px, area = (left + right) / 2.0, max(right - left, 1e-9) * max(bottom - top, 1e-9)
    for other in others_px:
        o_left, o_top, o_right, o_bottom = (float(v) for v in other)
        if o_left < x_px < o_right and o_top < bottom < o_bottom:
            return "box bottom inside another person's box"
        overlap_w = min(right, o_right) - max(left, o_left)
        overlap_h = min(bottom, o_bottom) - max(top, o_top)
        if overlap_w > 0 and overlap_h > 0 and overlap_w * overlap_h > BOX_INSIDE_FRACTION * area:
            return "box mostly inside another person's box"
    front = others_px if front_px is None else front_px
    if len(front) and drawn_to_feet_in_front(box_px, np.asarray(front, dtype=float)):
        return "box ends level with the box of a person in front of it (drawn down to hidden feet)"
    return None


def as_static(person: PersonIn) -> PersonIn:
    """The person flagged static (found at a static spot: no evidence, no violation), placed as before."""
    return replace(person, unusable_reason=STATIC_REASON, static=True)


def person_from_centres(
    shoulder: Point | None, ankle: Point | None, image_size_px: tuple[int, int], *, track_id: str | None = None
) -> PersonIn:
    """A person posted as explicit centres (ankle None when hidden) as the store's row, with the verdict and the
    client's track id, if it gave one."""
    shoulder_px = None if shoulder is None else (float(shoulder[0]), float(shoulder[1]))
    ankle_px = None if ankle is None else (float(ankle[0]), float(ankle[1]))
    return PersonIn(
        shoulder_px=shoulder_px,
        ankle_px=ankle_px,
        unusable_reason=evidence_problem(shoulder_px, ankle_px, image_size_px),
        track_id=track_id,
        posture=_posted_posture(shoulder_px, ankle_px),
    )


def _unplace_repeats(
    people: Sequence[PersonIn], candidates: Sequence[int], same: Callable[[int, int], bool], why: str
) -> tuple[list[PersonIn], set[int]]:
    """The people with each candidate that repeats an earlier candidate (`same(a, b)` on positions in
    `candidates`, a before b, the first not itself a repeat) kept with the reason and without points; and the
    repeats' indices into `people`."""
    kept = list(people)
    repeats: set[int] = set()
    for b in range(1, len(candidates)):
        original = next((a for a in range(b) if candidates[a] not in repeats and same(a, b)), None)
        if original is not None:
            repeats.add(candidates[b])
            kept[candidates[b]] = replace(
                people[candidates[b]],
                shoulder_px=None,
                ankle_px=None,
                unusable_reason=f"same pose as person {candidates[original]} ({why})",
            )
    return kept, repeats


def drop_posted_repeats(people: Sequence[PersonIn]) -> list[PersonIn]:
    """A posted frame's people with any repeat of an earlier one unplaced: two people whose shoulder centres and
    ankle centres both lie within `DUPLICATE_POSE_FRACTION` of their shoulder-to-ankle length of each other are one
    body posted twice (a client's detector boxing one person twice), since two bodies cannot stand in one place.
    Measured, the second is a phantom a few centimetres from the first: a violation in every frame. As for image
    frames (`people_from_detections`), the repeat is kept, with the reason, and neither evidence nor placed.
    Vectorised (the API stores hundreds of frames a second): only people with both centres are compared."""
    whole = [i for i, person in enumerate(people) if person.shoulder_px is not None and person.ankle_px is not None]
    if len(whole) < 2:
        return list(people)
    shoulder_x, shoulder_y, ankle_x, ankle_y = np.array(
        [(*people[i].shoulder_px, *people[i].ankle_px) for i in whole],  # type: ignore[misc]
        dtype=float,
    ).T
    length2 = (ankle_x - shoulder_x) ** 2 + (ankle_y - shoulder_y) ** 2
    limit2 = DUPLICATE_POSE_FRACTION**2 * np.maximum.outer(length2, length2)
    # One n x n array at a time: numpy hands the interpreter lock to other threads around loops over more than
    # 500 elements, and the API's event loop then waits for the frame writer's thread to give it back (up to the
    # 5 ms switch interval); an (n, n, 2) array of a 16-person frame is already past that.
    close = np.triu(_squared_gaps(ankle_x, ankle_y) < limit2, 1)
    if not close.any():  # almost every frame: no two ankle centres that close
        return list(people)
    close &= _squared_gaps(shoulder_x, shoulder_y) < limit2
    kept, _ = _unplace_repeats(people, whole, lambda a, b: bool(close[a, b]), "posted twice")
    return kept


def _squared_gaps(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n, n) squared distances between n points."""
    dx, dy = np.subtract.outer(x, x), np.subtract.outer(y, y)
    return dx * dx + dy * dy


def _same_pose(a: PersonIn, b: PersonIn) -> bool:
    """Whether two detections' keypoints describe one pose (see the module docstring), or place them at one point."""
    if a.keypoints is None or b.keypoints is None or a.box_px is None or b.box_px is None:
        return False
    scale_px = max(a.box_px[3] - a.box_px[1], b.box_px[3] - b.box_px[1])
    for point_a, point_b in ((a.shoulder_px, b.shoulder_px), (a.ankle_px, b.ankle_px)):
        if point_a is not None and point_b is not None:
            if math.hypot(point_a[0] - point_b[0], point_a[1] - point_b[1]) < DUPLICATE_POSE_FRACTION * scale_px:
                return True
    ka, kb = np.asarray(a.keypoints, dtype=float), np.asarray(b.keypoints, dtype=float)
    shared = (ka[:, 2] >= MIN_SCORE) & (kb[:, 2] >= MIN_SCORE)
    if shared.sum() < MIN_SHARED_KEYPOINTS:
        return False
    gap_px = float(np.median(np.hypot(*(ka[shared, :2] - kb[shared, :2]).T)))
    return gap_px < DUPLICATE_POSE_FRACTION * scale_px


def people_from_detections(found: Sequence[DetectedPerson], image_size_px: tuple[int, int]) -> list[PersonIn]:
    """A frame's people as the store's rows: each person's verdict, and repeated poses dropped (module docstring).

    `found` is in the pose estimator's order, most confident detection first, so a pose is compared with the
    ones before it and the more confident detection keeps it.
    """
    people = [person_from_detection(person, image_size_px) for person in found]

    def same(a: int, b: int) -> bool:
        return _same_pose(people[a], people[b])

    why = "a repeated detection, or a neighbour's pose"
    people, repeats = _unplace_repeats(people, range(len(people)), same, why)
    return place_from_boxes(people, image_size_px, repeats=repeats)


def place_from_boxes(
    people: Sequence[PersonIn], image_size_px: tuple[int, int], *, repeats: Collection[int] = ()
) -> list[PersonIn]:
    """People the pose could not put on the ground, placed from their detector box's bottom where it is a contact.

    A person without trusted ankles (shoulders not read, legs hidden or folded out of sight) is otherwise placed
    from their shoulders with a height prior, or not at all, and an unplaced person never takes part in a
    violation. The box's bottom centre is where a standing or seated person meets the ground when nothing cuts
    it (`box_bottom_problem`): it becomes their ankle point, moved up by `BOX_ANKLE_OFFSET` of the box height
    (the feet reach below the ankle centre), `placed_from_box`, so that they are measured, with the wider sigma
    of the cue (service/frames/measure.py), and never calibrated on. On Town Centre the box bottom places a
    person 0.15-0.17 m from their ankles (median by size; the shoulders at the height prior: 0.17-0.28 m), so it
    replaces the shoulders too, unless the shoulders sit low in the box (`BOX_MIN_SHOULDER_DROP`: the box ends
    at a wall or a table, not at the feet). A repeated pose (`repeats`: a phantom of one person), a box the
    detector doubts with nothing the pose vouches for (`BOX_MIN_SCORE`) and a box that is not a contact keep what
    they had: shoulders, or nothing. Measured on Town Centre: docs/benchmarks/pose.md, "Placing the people the pose
    cannot read".
    """
    boxes = [person.box_px for person in people]
    placed = []
    for index, person in enumerate(people):
        box = person.box_px
        if (
            person.ankle_px is not None
            or box is None
            or index in repeats
            or (person.shoulder_px is None and (person.detection_score or 0.0) < BOX_MIN_SCORE)
        ):
            placed.append(person)
            continue
        others = [other for j, other in enumerate(boxes) if j != index and other is not None]
        front = [
            other.box_px
            for j, other in enumerate(people)
            if j != index and other.box_px is not None and (other.detection_score or 1.0) >= BOX_MIN_SCORE
        ]
        left, top, right, bottom = box
        shoulder = person.shoulder_px
        cut = shoulder is not None and bottom - shoulder[1] < BOX_MIN_SHOULDER_DROP * (bottom - top)
        if cut or box_bottom_problem(box, others, image_size_px, front) is not None:
            placed.append(person)
            continue
        contact = ((left + right) / 2.0, bottom - BOX_ANKLE_OFFSET * (bottom - top))
        placed.append(replace(person, ankle_px=contact, unusable_reason=BOX_REASON, placed_from_box=True))
    return placed
