"""Which keypoints of a frame's people were seen, and who stands (pure numpy, one frame at a time).

A single-person pose model always answers 17 points; where a joint was hidden it guesses, and the guess can be
confident. Two guesses hurt: ankles guessed at the hip of the person in front (a "violation" of 0.1 m between two
people walking one behind the other), and legs guessed under a table or a coat (a seated person taken for a
standing one, whose shoulder-to-ankle segment then poisons the calibration). Rules, per keypoint:

- Seen: score >= `MIN_SCORE` (0.3, the usual MoveNet visibility cut).
- Not someone else's: a keypoint inside the box of a person in front (their box reaches lower in the frame by at
  least `FRONT_MARGIN` of this person's height: nearer the camera, for a camera above the people) may be that
  person's limb; it is not trusted. The box is shrunk by `OCCLUDER_SHRINK` of its width on each side, so that a
  hand brushing a neighbour's box edge stays trusted.
- Its own: a keypoint further outside the person's own box than `SIDE_MARGIN` of the box height at the sides, or
  `END_MARGIN` above or below it, is a neighbour's limb or a guess, not trusted. Joints lie inside the silhouette
  the detector boxed; MoveNet's square crop holds more than the box, and reads a neighbour's foot beside it as an
  ankle (Town Centre frames 90 and 125: two walkers, each a `standing` person with one ankle on the foot of the
  person beside them, 0.3 and 0.4 of their height outside their box) or a whole neighbour for a box around a
  bicycle or a half-seen person (frame 90, the atrium). The ends get more room: on a steep view the shoulders of a
  small person reach the top of a box drawn around a bent head.
- Ankles need their leg: an ankle is trusted only with its knee, and in order down the body (hip above knee
  above ankle in the image, as for any camera looking down at people: the vertical vanishing point lies below).
  A hidden leg is guessed as a whole, so a guessed ankle rarely has a confident knee above it.
- In view: a person whose box reaches the bottom edge of the frame is cut by it, and the model guesses their
  feet at the edge: their knees and ankles are not trusted.

Posture, from the trusted keypoints (`Posture`):
- `standing`: both shoulders and both ankles trusted, and the legs extended (hip-centre-to-ankle-centre at least
  `LEG_TO_TORSO` times shoulder-to-hip: ~1.5 for a standing adult, under ~1 for a seated or crouching one, whose
  thighs point at the camera or sideways). Only these are calibration evidence.
- `seated`: shoulders trusted, legs seen (a knee or an ankle trusted) but bent. Seated or crouching: a position
  from the ankles when they are trusted (feet on the ground), else from the shoulders with a seated height prior.
- `partial`: shoulders trusted, the lower body not (hidden behind someone, a table, the frame edge, or seen from
  so far above that the legs are behind the head): a position from the shoulders only.
- `unknown`: shoulders not trusted (a back turned to a steep camera, a box around something that is not a
  person): the pose is too uncertain to place.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from service.domain import Posture

MIN_SCORE: Final = 0.3
FRONT_MARGIN: Final = 0.05
OCCLUDER_SHRINK: Final = 0.1
LEG_TO_TORSO: Final = 1.0
BOTTOM_EDGE_PX: Final = 2.0
SIDE_MARGIN: Final = 0.05
END_MARGIN: Final = 0.1
ORDER_TOLERANCE: Final = 0.05
"""Slack of the hip-above-knee-above-ankle order, as a fraction of the box height."""

SHOULDERS: Final = (5, 6)
HIPS: Final = (11, 12)
KNEES: Final = (13, 14)
ANKLES: Final = (15, 16)


@dataclass(frozen=True)
class Assessment:
    trusted: np.ndarray
    """(17,) bool."""
    posture: Posture
    occluded: np.ndarray
    """(17,) bool: seen, but inside the box of a person in front."""


def _occluders(boxes: np.ndarray, index: int) -> np.ndarray:
    """Boxes of the people in front of person `index`, shrunk at the sides (see the module docstring)."""
    own = boxes[index]
    height = own[3] - own[1]
    front = boxes[:, 3] >= own[3] + FRONT_MARGIN * height
    front[index] = False
    shrunk = boxes[front].copy()
    width = shrunk[:, 2] - shrunk[:, 0]
    shrunk[:, 0] += OCCLUDER_SHRINK * width
    shrunk[:, 2] -= OCCLUDER_SHRINK * width
    return shrunk


def assess_person(
    keypoints_px: np.ndarray,
    scores: np.ndarray,
    box_xyxy: Sequence[float],
    occluders: np.ndarray,
    image_height_px: float | None = None,
) -> Assessment:
    """Trusted keypoints and posture of one person, given the (shrunk) boxes of the people in front."""
    points = np.asarray(keypoints_px, dtype=np.float64).reshape(17, 2)
    seen = np.asarray(scores, dtype=np.float64).reshape(17) >= MIN_SCORE
    if image_height_px is not None and box_xyxy[3] >= image_height_px - BOTTOM_EDGE_PX:
        seen[list(KNEES + ANKLES)] = False  # cut by the frame: the legs below it are guesses
    left, top, right, bottom = (float(v) for v in box_xyxy)
    side, end = SIDE_MARGIN * (bottom - top), END_MARGIN * (bottom - top)
    seen &= (points[:, 0] >= left - side) & (points[:, 0] <= right + side)
    seen &= (points[:, 1] >= top - end) & (points[:, 1] <= bottom + end)
    inside = np.zeros(17, dtype=bool)
    for left, top, right, bottom in np.asarray(occluders, dtype=np.float64).reshape(-1, 4):
        inside |= (points[:, 0] > left) & (points[:, 0] < right) & (points[:, 1] > top) & (points[:, 1] < bottom)
    occluded = seen & inside
    trusted = seen & ~inside
    slack = ORDER_TOLERANCE * (box_xyxy[3] - box_xyxy[1])
    for hip, knee, ankle in zip(HIPS, KNEES, ANKLES, strict=True):
        if not trusted[ankle]:
            continue
        in_order = trusted[knee] and points[knee, 1] <= points[ankle, 1] + slack
        if trusted[hip]:
            in_order = in_order and points[hip, 1] <= points[knee, 1] + slack
        trusted[ankle] = in_order
    return Assessment(trusted=trusted, posture=_posture(points, trusted), occluded=occluded)


def _centre(points: np.ndarray, trusted: np.ndarray, pair: tuple[int, int]) -> np.ndarray | None:
    """Mean of the trusted keypoints of a pair (one is enough for hips), None if neither is trusted."""
    chosen = [k for k in pair if trusted[k]]
    return points[chosen].mean(axis=0) if chosen else None


def _posture(points: np.ndarray, trusted: np.ndarray) -> Posture:
    if not trusted[list(SHOULDERS)].all():
        return "unknown"
    legs_seen = trusted[list(KNEES)].any() or trusted[list(ANKLES)].any()
    if not trusted[list(ANKLES)].all():
        return "seated" if legs_seen and _bent(points, trusted) else "partial"
    return "seated" if _bent(points, trusted) else "standing"


def _bent(points: np.ndarray, trusted: np.ndarray) -> bool:
    """Whether the seen legs are folded: the lowest seen leg point is closer to the hips than the torso is long."""
    shoulder = points[list(SHOULDERS)].mean(axis=0)
    hip = _centre(points, trusted, HIPS)
    if hip is None:
        return False
    torso = float(np.hypot(*(hip - shoulder)))
    low = _centre(points, trusted, ANKLES)
    if low is None:
        low = _centre(points, trusted, KNEES)
        if low is None:
            return False
        # A knee is about half way down a straight leg.
        return float(np.hypot(*(low - hip))) * 2.0 < LEG_TO_TORSO * torso
    return float(np.hypot(*(low - hip))) < LEG_TO_TORSO * torso


def assess_frame(
    boxes_xyxy: np.ndarray, keypoints_px: np.ndarray, scores: np.ndarray, image_height_px: float | None = None
) -> list[Assessment]:
    """One assessment per person of a frame (boxes (N, 4), keypoints (N, 17, 2), scores (N, 17))."""
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    return [
        assess_person(keypoints_px[i], scores[i], boxes[i], _occluders(boxes, i), image_height_px)
        for i in range(len(boxes))
    ]
