"""The static-spot rule on plain values (service.cameras.static_spots has the story): matching boxes to spots, and
the rule over a whole recording for `posemetry analyze`, which must not reach the store.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import numpy as np

from service.pose.merge import iou_matrix

SAME_PLACE_IOU: Final = 0.8
"""A still object's boxes in two frames overlap by 0.9 and more (detector jitter of a few pixels); a walking
person's boxes a fifth of a second apart by less than 0.7."""
MIN_SIGHTINGS: Final = 3
FORGET_AFTER_S: Final = 60.0
KEYPOINT_SAMPLE_S: Final = 10.0
"""Keypoint frames (a client's own pose model) come at several a second per camera, and a spot needs a sighting
only within every FORGET_AFTER_S: one keypoint frame per this many seconds of frame time is recorded, so a busy
camera's spots table holds a few samples of its passers-by instead of one row per person per frame. Six samples per
FORGET_AFTER_S let a still object be missed by the client's detector five times in a row and stay one spot."""
# A keypoint person's box from their two centres: a body's width (half of it either side of the segment's middle)
# and the head above the shoulders, as shares of the segment. Each edge rests on an average of the centres or on
# the segment's length, so a still body's keypoint jitter of 1-2 % of the segment moves the box less than its own
# noise (IoU about 0.9 with its first box), while a walker's ankles move a body width a second.
_CENTRE_BOX_HALF_WIDTH = 0.25
_CENTRE_BOX_HEAD = 0.25

Box = tuple[float, float, float, float]


def centre_box(shoulder_px: tuple[float, float], ankle_px: tuple[float, float]) -> Box:
    """The box a person posted as keypoints stands in, from their shoulder and ankle centres (no detector box)."""
    (sx, sy), (ax, ay) = shoulder_px, ankle_px
    length = float(np.hypot(sx - ax, sy - ay))
    middle, half = 0.5 * (sx + ax), _CENTRE_BOX_HALF_WIDTH * length
    return (middle - half, min(sy, ay) - _CENTRE_BOX_HEAD * length, middle + half, max(sy, ay))


def match_spots(boxes: Sequence[Box], spots: Sequence[Box] | np.ndarray) -> list[int | None]:
    """For each box, the spot it is another sighting of (an index into `spots`), or None: greedy by overlap."""
    matched: list[int | None] = [None] * len(boxes)
    if len(boxes) == 0 or len(spots) == 0:
        return matched
    overlap = iou_matrix(np.asarray(boxes, dtype=float), np.asarray(spots, dtype=float))
    taken: set[int] = set()
    for flat in np.argsort(-overlap, axis=None):
        box, spot = divmod(int(flat), len(spots))
        if overlap[box, spot] < SAME_PLACE_IOU:
            break
        if matched[box] is None and spot not in taken:
            matched[box] = spot
            taken.add(spot)
    return matched


def static_in_recording(
    times_s: Sequence[float], boxes: Sequence[Sequence[Box | None]], static_after_s: float
) -> list[list[bool]]:
    """Offline, the same rule on a whole recording (`posemetry analyze`): for each frame (times_s, in order) and
    each of its boxes, whether it stands at a static spot.

    Spots are matched, counted and forgotten as `observe` does, frame by frame. The verdict differs in one way:
    the service decides as frames arrive, so a mannequin gives evidence until its spot has stood for
    static_after_s; a recording is known whole, so every sighting of a spot that turns out static is marked.
    """
    firsts = np.zeros((16, 4))  # per spot (grown by doubling): its first box, first and last sighting
    first_seen, last_seen = np.zeros(16), np.zeros(16)
    sightings: list[list[tuple[int, int]]] = []
    live = np.zeros(0, dtype=int)  # spots seen within FORGET_AFTER_S, pruned frame by frame
    for frame, (at, frame_boxes) in enumerate(zip(times_s, boxes, strict=True)):
        live = live[last_seen[live] >= at - FORGET_AFTER_S]
        present = [(index, box) for index, box in enumerate(frame_boxes) if box is not None]
        matches = match_spots([box for _, box in present], firsts[live])
        for (index, box), match in zip(present, matches, strict=True):
            if match is None:
                spot = len(sightings)
                if spot == len(firsts):
                    firsts, first_seen, last_seen = (
                        np.concatenate((a, np.zeros_like(a))) for a in (firsts, first_seen, last_seen)
                    )
                firsts[spot], first_seen[spot] = box, at
                sightings.append([])
                live = np.append(live, spot)
            else:
                spot = int(live[match])
            last_seen[spot] = at
            sightings[spot].append((frame, index))
    static = [[False] * len(frame_boxes) for frame_boxes in boxes]
    for spot, seen in enumerate(sightings):
        if len(seen) >= MIN_SIGHTINGS and last_seen[spot] - first_seen[spot] >= static_after_s:
            for frame, index in seen:
                static[frame][index] = True
    return static
