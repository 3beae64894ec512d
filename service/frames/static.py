"""Static spots for keypoint frames: a client's own pose model finds the shop window's mannequin too.

Image frames meet the camera's static spots in the pose job, before their people are stored
(service.frames.detection). Keypoint frames are stored by the API the moment they arrive, at hundreds a second, so
they meet them in the measuring job instead, a chunk at a time:

- every person of a measured keypoint frame whose box (from their centres: no detector box was posted,
  static_rule.centre_box) lies on a static spot is static: measured like anyone, but no violation, and their stored
  observation stops being calibration evidence (the camera's evidence counter with it);
- one keypoint frame per KEYPOINT_SAMPLE_S of frame time records its boxes as sightings (cameras.static_spots.observe),
  which is all a spot needs to stand for `static_after_s` and keeps a busy camera's spots table small.

A mannequin's sightings before its spot turned static stay evidence, as for image frames: the calibration counts
repeats once (service.geometry.evidence), so a still figure is one person in a solve, not hundreds.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from sqlalchemy import false, func, select, true, update
from sqlalchemy.orm import Session

from service.cameras.static_rule import KEYPOINT_SAMPLE_S, MIN_SIGHTINGS, Box, centre_box, match_spots
from service.cameras.static_spots import is_static, observe
from service.frames.keypoints import STATIC_REASON
from service.store.models import Camera, Frame, Observation, StaticSpot


@dataclass(frozen=True)
class SpotsSeen:
    """The camera's spots as a measuring chunk read them: the static ones' boxes, and the latest sighting."""

    static_boxes: list[Box]
    last_sighting: datetime | None


@dataclass
class StaticMarks:
    """What a chunk's keypoint frames owe the static spots (see the module docstring)."""

    static: dict[uuid.UUID, list[int]] = field(default_factory=dict)
    """Per frame, the indices of its people standing at a static spot."""
    samples: list[tuple[datetime, list[Box | None]]] = field(default_factory=list)
    """The frames whose boxes are recorded as sightings: (frame time, a box per person or None)."""

    def people(self, frame_id: uuid.UUID, people: Sequence[Any]) -> Sequence[Any]:
        """A frame's stored people, those at a static spot carrying the static reason (what measuring reads)."""
        marked = set(self.static.get(frame_id, ()))
        if not marked:
            return people
        return [_Static.of(person) if index in marked else person for index, person in enumerate(people)]


@dataclass(frozen=True)
class _Static:
    """A stored person's centres, marked static (service.domain.StoredCentres)."""

    shoulder_x_px: float | None
    shoulder_y_px: float | None
    ankle_x_px: float | None
    ankle_y_px: float | None
    client_track_id: str | None
    posture: str | None
    placed_from_box: bool
    unusable_reason: str | None = STATIC_REASON
    static: bool = True

    @classmethod
    def of(cls, person: Any) -> _Static:
        return cls(
            person.shoulder_x_px,
            person.shoulder_y_px,
            person.ankle_x_px,
            person.ankle_y_px,
            person.client_track_id,
            person.posture,
            person.placed_from_box,
        )


def spots_seen(session: Session, camera_id: str, static_after_s: float) -> SpotsSeen:
    """Two light reads per chunk (a measuring job may take a chunk of one frame): the spots seen often enough to be
    static, as plain rows, and the latest sighting (passers-by's spots, most of the table, are seen once)."""
    spot = StaticSpot.__table__.c
    box = (spot.left_px, spot.top_px, spot.right_px, spot.bottom_px)
    candidates = session.execute(
        select(*box, spot.first_seen, spot.last_seen, spot.sightings).where(
            spot.camera_id == camera_id, spot.sightings >= MIN_SIGHTINGS
        )
    ).all()
    return SpotsSeen(
        [(s.left_px, s.top_px, s.right_px, s.bottom_px) for s in candidates if is_static(s, static_after_s)],
        session.scalar(select(func.max(spot.last_seen)).where(spot.camera_id == camera_id)),
    )


def _box(person: Any) -> Box | None:
    if None in (person.shoulder_x_px, person.shoulder_y_px, person.ankle_x_px, person.ankle_y_px):
        return None
    return centre_box((person.shoulder_x_px, person.shoulder_y_px), (person.ankle_x_px, person.ankle_y_px))


def mark_keypoint_frames(spots: SpotsSeen, frames: Sequence[Frame], people: dict[uuid.UUID, list[Any]]) -> StaticMarks:
    """The static people of the chunk's keypoint frames, and which of those frames to record as sightings."""
    marks = StaticMarks()
    last = spots.last_sighting
    for frame in sorted((f for f in frames if f.source == "keypoints"), key=lambda f: f.timestamp):
        due = last is None or (frame.timestamp - last).total_seconds() >= KEYPOINT_SAMPLE_S
        if not (due or spots.static_boxes):
            continue  # most frames of a camera without static spots: nothing to match, nothing to record
        boxes = [_box(person) for person in people.get(frame.id, [])]
        present = [(index, box) for index, box in enumerate(boxes) if box is not None]
        if spots.static_boxes and present:
            matches = match_spots([box for _, box in present], spots.static_boxes)
            static = [index for (index, _), match in zip(present, matches, strict=True) if match is not None]
            if static:
                marks.static[frame.id] = static
        if present and due:
            marks.samples.append((frame.timestamp, boxes))
            last = frame.timestamp
    return marks


def record_static_marks(session: Session, camera: Camera, marks: StaticMarks, static_after_s: float) -> None:
    """In the chunk's transaction: the sightings, and the static people's observations out of the evidence.

    Only observations still usable in the camera's epoch leave its counter (older epochs' people feed no solve), so
    a frame measured again (after a reset or a move) is not subtracted twice."""
    for at, boxes in marks.samples:
        observe(session, camera.id, at, boxes, static_after_s)
    withdrawn = 0
    for frame_id, indices in marks.static.items():
        person = (Observation.frame_id == frame_id, Observation.person_index.in_(indices))
        session.execute(
            update(Observation)
            .where(*person, Observation.usable == false())
            .values(unusable_reason=STATIC_REASON, static=True)
            .execution_options(synchronize_session=False)
        )
        withdrawn += session.execute(
            update(Observation)
            .where(*person, Observation.usable == true(), Observation.epoch == camera.epoch)
            .values(usable=False, unusable_reason=STATIC_REASON, static=True)
            .execution_options(synchronize_session=False)
        ).rowcount
    if withdrawn:
        session.execute(
            update(Camera)
            .where(Camera.id == camera.id)
            .values(usable_evidence_count=Camera.usable_evidence_count - withdrawn)
            .execution_options(synchronize_session=False)
        )
