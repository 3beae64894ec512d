"""A person partly hidden behind a nearer one, read again with the nearer person masked out of the crop (numpy).

MoveNet SinglePose answers one pose per crop, the most salient person's, and a hidden person's square crop also
holds the person in front of them, whole and usually nearer its centre. On Town Centre (frames 42-54, the woman
walking behind the woman in red) MoveNet reads the nearer woman in the hidden woman's crop: her pose is then a
copy (`same pose as person N`, service/frames/keypoints.py), and she is neither placed nor evidence. Reading her on
her upper-body box instead changes nothing: the square around it still holds the nearer woman's head.

So the crop is changed, not the box: the nearer person's box is filled with black (`MASK_FILL`, what the crop
already holds where it leaves the image; mid-grey read the same on Town Centre), and the hidden person is read
again from what is left: their own head and shoulders above the nearer person.

Who is nearer (`nearer_people`): for a camera above the people, looking down at a ground plane, a person further
away appears higher in the image at both ends, head and feet. Person i is in front of person j when their boxes
overlap by at least `MIN_OVERLAP` of j's box, i's top lies at least `TOP_MARGIN` of j's height below j's top (j's
head shows above i: there is something of j to read) and i reaches at least as low as j, within `BOTTOM_TOLERANCE`
of j's height (j's box may be amodal, guessed down to the hidden feet behind i: on frame 48 the hidden woman's
box ends 6 px above the nearer woman's). It needs no pose and no calibration, and it is the same physics as the
occluders of assess.py, told from the top of the box because the bottom of a hidden person's box is a guess.

Who is read again (`needs_reading`): only a person today's reading loses: a pose that repeats the pose of a nearer
person found more confidently (`is_copy`; people come most confident first, and the repeated-pose rule of
frames/keypoints.py keeps the pose for the more confident one), or shoulders not trusted (posture `unknown`). A
person whose pose was usable keeps it untouched: re-reading a mannequin that kept its pose against a less confident
copy beside it (Town Centre frame 24) moved its keypoints, and the copy, no longer a copy, stood 0.07 m from it.

Which masked reading is kept (`accept`): both shoulders confident (score >= `MIN_SCORE`), neither inside a masked
box (shrunk at the sides as in assess.py: a shoulder in the black fill is a guess), both inside the person's own box
and in its upper part (`MAX_SHOULDER_DEPTH`), and not a copy of anyone else's pose in the frame. Otherwise the first
reading stays, so a failed attempt changes nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from .assess import MIN_SCORE, OCCLUDER_SHRINK, SHOULDERS, Assessment

MIN_OVERLAP: Final = 0.2
"""Share of the hidden person's box area the nearer person's box must cover to be worth masking."""
TOP_MARGIN: Final = 0.1
"""How far below the hidden person's box top the nearer person's top must lie, as a fraction of the hidden
person's box height (their head, ~0.15 of the height, must partly show above the nearer person)."""
BOTTOM_TOLERANCE: Final = 0.05
"""How far above the hidden person's box bottom the nearer person's bottom may end (the hidden box is often
amodal, down to the guessed feet), as a fraction of the hidden person's box height."""
MASK_FILL: Final = 0
"""Value written over the nearer person's pixels: the crop's own fill outside the image (movenet.extract_crop)."""
COPY_FRACTION: Final = 0.05
"""Two poses are one when their shoulder centres, or the median of their shared confident keypoints, lie closer
than this fraction of the taller box (service/frames/keypoints.py, DUPLICATE_POSE_FRACTION)."""
MIN_SHARED_KEYPOINTS: Final = 4
MAX_SHOULDER_DEPTH: Final = 0.4
"""Lowest place of a kept reading's shoulder centre in the hidden person's own box, as a fraction of its height
below the top: their head shows above the nearer person, so their shoulders lie in the box's upper part (0.19 of
the height for a whole standing person on Town Centre, 0.27 for frame 54's upper-body box). A reading whose
shoulders lie elsewhere (above the box, on a bag in front of it) is someone or something else."""


def _height(box: np.ndarray) -> float:
    return float(box[3] - box[1])


def in_front(own_xyxy_px: Sequence[float] | np.ndarray, others_xyxy_px: np.ndarray) -> np.ndarray:
    """(N,) bool: which of the other boxes belong to people in front of the box `own`, covering enough of it.

    With level bottoms, also what makes `own`'s bottom a guess (`drawn_to_feet_in_front`).
    """
    own = np.asarray(own_xyxy_px, dtype=np.float64).reshape(4)
    boxes = np.asarray(others_xyxy_px, dtype=np.float64).reshape(-1, 4)
    height = _height(own)
    area = max((own[2] - own[0]) * height, 1e-9)
    width_in = np.minimum(boxes[:, 2], own[2]) - np.maximum(boxes[:, 0], own[0])
    height_in = np.minimum(boxes[:, 3], own[3]) - np.maximum(boxes[:, 1], own[1])
    overlap = np.clip(width_in, 0, None) * np.clip(height_in, 0, None)
    return (
        (overlap >= MIN_OVERLAP * area)
        & (boxes[:, 1] >= own[1] + TOP_MARGIN * height)
        & (boxes[:, 3] >= own[3] - BOTTOM_TOLERANCE * height)
    )


def drawn_to_feet_in_front(own_xyxy_px: Sequence[float] | np.ndarray, others_xyxy_px: np.ndarray) -> bool:
    """Whether the box `own` ends level with the box of a person in front of it (`in_front`, bottoms within
    `BOTTOM_TOLERANCE` of its height): a person further away has their feet higher in the image than the person
    in front, so such a box was drawn down to hidden feet, and its bottom is no ground contact. A box ending
    clearly above (its bottom inside the other box: frames/keypoints.py's own rule) or below the other's is not
    this case: on the steep atrium a walker beside a nearer one keeps the box bottom his feet make."""
    own = np.asarray(own_xyxy_px, dtype=np.float64).reshape(4)
    boxes = np.asarray(others_xyxy_px, dtype=np.float64).reshape(-1, 4)
    level = np.abs(boxes[:, 3] - own[3]) <= BOTTOM_TOLERANCE * _height(own)
    return bool((in_front(own, boxes) & level).any())


def nearer_people(boxes_xyxy_px: np.ndarray, index: int) -> np.ndarray:
    """Indices of the people in front of person `index` whose boxes cover enough of theirs (module docstring)."""
    boxes = np.asarray(boxes_xyxy_px, dtype=np.float64).reshape(-1, 4)
    front = in_front(boxes[index], boxes)
    front[index] = False
    return np.flatnonzero(front)


def fill_boxes(square: np.ndarray, x0_px: int, y0_px: int, boxes_xyxy_px: np.ndarray) -> np.ndarray:
    """`square` (a crop whose top-left pixel is image pixel (x0, y0)) with each box's pixels set to `MASK_FILL`.

    A box covers the image pixels whose centres it contains: columns round(left)..round(right) - 1. Parts of a box
    outside the square are ignored. Modifies and returns `square`.
    """
    side_y, side_x = square.shape[:2]
    for left, top, right, bottom in np.asarray(boxes_xyxy_px, dtype=np.float64).reshape(-1, 4):
        col_lo, col_hi = max(round(left) - x0_px, 0), min(round(right) - x0_px, side_x)
        row_lo, row_hi = max(round(top) - y0_px, 0), min(round(bottom) - y0_px, side_y)
        if col_hi > col_lo and row_hi > row_lo:
            square[row_lo:row_hi, col_lo:col_hi] = MASK_FILL
    return square


def _shoulder_centre(keypoints_px: np.ndarray, scores: np.ndarray) -> np.ndarray | None:
    shoulders = list(SHOULDERS)
    if (scores[shoulders] < MIN_SCORE).any():
        return None
    return keypoints_px[shoulders].mean(axis=0)


def is_copy(
    keypoints_a_px: np.ndarray,
    scores_a: np.ndarray,
    box_a: np.ndarray,
    keypoints_b_px: np.ndarray,
    scores_b: np.ndarray,
    box_b: np.ndarray,
) -> bool:
    """Whether two readings are one pose: confident shoulder centres, or the median of the shared confident
    keypoints, closer than `COPY_FRACTION` of the taller box (the repeated-pose test of frames/keypoints.py)."""
    scale_px = COPY_FRACTION * max(_height(np.asarray(box_a)), _height(np.asarray(box_b)))
    centre_a, centre_b = _shoulder_centre(keypoints_a_px, scores_a), _shoulder_centre(keypoints_b_px, scores_b)
    if centre_a is not None and centre_b is not None and float(np.hypot(*(centre_a - centre_b))) < scale_px:
        return True
    shared = (scores_a >= MIN_SCORE) & (scores_b >= MIN_SCORE)
    if shared.sum() < MIN_SHARED_KEYPOINTS:
        return False
    gap_px = np.hypot(*(keypoints_a_px[shared] - keypoints_b_px[shared]).T)
    return float(np.median(gap_px)) < scale_px


def _shrunk(boxes: np.ndarray) -> np.ndarray:
    shrunk = np.asarray(boxes, dtype=np.float64).reshape(-1, 4).copy()
    width = shrunk[:, 2] - shrunk[:, 0]
    shrunk[:, 0] += OCCLUDER_SHRINK * width
    shrunk[:, 2] -= OCCLUDER_SHRINK * width
    return shrunk


@dataclass(frozen=True)
class Hidden:
    """A person to read again, and the nearer people whose boxes are masked out of their crop."""

    index: int
    nearer: np.ndarray
    """Indices of the nearer people."""


def needs_reading(
    boxes_xyxy_px: np.ndarray,
    keypoints_px: np.ndarray,
    scores: np.ndarray,
    assessments: Sequence[Assessment],
) -> list[Hidden]:
    """The people whose reading is lost (a nearer person's pose, or shoulders not trusted) and who have someone
    nearer to mask out (module docstring)."""
    boxes = np.asarray(boxes_xyxy_px, dtype=np.float64).reshape(-1, 4)
    hidden = []
    for j in range(len(boxes)):
        nearer = nearer_people(boxes, j)
        if nearer.size == 0:
            continue
        copied = any(
            is_copy(keypoints_px[j], scores[j], boxes[j], keypoints_px[i], scores[i], boxes[i]) for i in nearer if i < j
        )
        if copied or assessments[j].posture == "unknown":
            hidden.append(Hidden(j, nearer))
    return hidden


def accept(
    hidden: Hidden,
    keypoints_px: np.ndarray,
    scores: np.ndarray,
    boxes_xyxy_px: np.ndarray,
    frame_keypoints_px: np.ndarray,
    frame_scores: np.ndarray,
) -> bool:
    """Whether the masked reading (`keypoints_px`, `scores`) of `hidden` is their own pose (module docstring)."""
    boxes = np.asarray(boxes_xyxy_px, dtype=np.float64).reshape(-1, 4)
    shoulders = list(SHOULDERS)
    if (scores[shoulders] < MIN_SCORE).any():
        return False
    x, y = keypoints_px[shoulders, 0], keypoints_px[shoulders, 1]
    for left, top, right, bottom in _shrunk(boxes[hidden.nearer]):
        if ((x > left) & (x < right) & (y > top) & (y < bottom)).any():
            return False
    own = boxes[hidden.index]
    depth = (float(y.mean()) - own[1]) / _height(own)
    if (x < own[0]).any() or (x > own[2]).any() or not 0.0 <= depth <= MAX_SHOULDER_DEPTH:
        return False
    others = (i for i in range(len(boxes)) if i != hidden.index)
    return not any(is_copy(keypoints_px, scores, own, frame_keypoints_px[i], frame_scores[i], boxes[i]) for i in others)
