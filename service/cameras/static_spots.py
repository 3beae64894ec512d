"""Static spots: a "person" the detector finds in the same place frame after frame is not a person.

Mannequins in a shop window, a poster, a statue: the detector sees a person there in every frame, the pose model
reads a plausible body, and they would stand as calibration evidence and raise violations with everyone walking
past. What gives them away is that they never move. Each image frame's boxes are matched to the camera's spots:
a box overlapping a spot's first box by `SAME_PLACE_IOU` or more is another sighting of it (the spot keeps its
first box, so a person shuffling slowly cannot drag a spot along with them); any other box opens a new spot. A spot
seen over `Settings.static_after_s` of frame time, at least `MIN_SIGHTINGS` times, is static, and the people found
there are marked (`STATIC_REASON`): no evidence, no violation. A spot not seen for `FORGET_AFTER_S` of frame time
is forgotten (a person who stood still and walked away leaves nothing behind; a detector misses a still object
for a few frames at most), which also keeps a busy camera's table small: the spots of passers-by last a minute.

Frame time, not the clock: a camera's frames replayed or posted late give the same verdict.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime, timedelta
from typing import Final

import numpy as np
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from service.pose.merge import iou_matrix
from service.store.models import StaticSpot

SAME_PLACE_IOU: Final = 0.8
"""A still object's boxes in two frames overlap by 0.9 and more (detector jitter of a few pixels); a walking
person's boxes a fifth of a second apart by less than 0.7."""
MIN_SIGHTINGS: Final = 3
FORGET_AFTER_S: Final = 60.0

Box = tuple[float, float, float, float]


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


def is_static(spot: StaticSpot, static_after_s: float) -> bool:
    return spot.sightings >= MIN_SIGHTINGS and (spot.last_seen - spot.first_seen).total_seconds() >= static_after_s


def observe(
    session: Session, camera_id: str, at: datetime, boxes: Sequence[Box | None], static_after_s: float
) -> list[bool]:
    """Record one frame's boxes (taken at `at`) against the camera's spots; whether each box is at a static spot.

    Boxes that are None (people posted without one) are neither matched nor recorded.
    """
    session.execute(
        delete(StaticSpot).where(
            StaticSpot.camera_id == camera_id, StaticSpot.last_seen < at - timedelta(seconds=FORGET_AFTER_S)
        )
    )
    spots = list(session.scalars(select(StaticSpot).where(StaticSpot.camera_id == camera_id).order_by(StaticSpot.id)))
    present = [(index, box) for index, box in enumerate(boxes) if box is not None]
    matches = match_spots([box for _, box in present], [(s.left_px, s.top_px, s.right_px, s.bottom_px) for s in spots])
    static = [False] * len(boxes)
    for (index, box), match in zip(present, matches, strict=True):
        if match is None:
            left, top, right, bottom = box
            session.add(
                StaticSpot(
                    camera_id=camera_id,
                    left_px=left,
                    top_px=top,
                    right_px=right,
                    bottom_px=bottom,
                    first_seen=at,
                    last_seen=at,
                    sightings=1,
                )
            )
            continue
        spot = spots[match]
        spot.first_seen, spot.last_seen = min(spot.first_seen, at), max(spot.last_seen, at)
        spot.sightings += 1
        static[index] = is_static(spot, static_after_s)
    session.flush()
    return static


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


def static_spots(session: Session, camera_id: str, static_after_s: float) -> list[StaticSpot]:
    """The camera's static spots, longest-standing first."""
    spots = session.scalars(select(StaticSpot).where(StaticSpot.camera_id == camera_id).order_by(StaticSpot.first_seen))
    return [spot for spot in spots if is_static(spot, static_after_s)]
