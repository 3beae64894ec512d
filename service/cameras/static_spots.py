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

Frame time, not the clock: a camera's frames replayed or posted late give the same verdict. Keypoint frames (no
detector box, hundreds a second) meet the same spots in the measuring job, sampled: service.frames.static.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Row, delete, select
from sqlalchemy.orm import Session

from service.store.models import StaticSpot

from .static_rule import FORGET_AFTER_S, MIN_SIGHTINGS, SAME_PLACE_IOU, Box, match_spots

__all__ = [
    "FORGET_AFTER_S",
    "MIN_SIGHTINGS",
    "SAME_PLACE_IOU",
    "Box",
    "is_static",
    "match_spots",
    "observe",
    "static_spots",
]


def is_static(spot: StaticSpot | Row[Any], static_after_s: float) -> bool:
    """A spot (or a row of its columns) seen often enough, over long enough."""
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


def static_spots(session: Session, camera_id: str, static_after_s: float) -> list[StaticSpot]:
    """The camera's static spots, longest-standing first."""
    spots = session.scalars(select(StaticSpot).where(StaticSpot.camera_id == camera_id).order_by(StaticSpot.first_seen))
    return [spot for spot in spots if is_static(spot, static_after_s)]
