"""Violation events in the store: a measured frame's close pairs, counted per time bucket, placed on the ground.

Functions flush but never commit: the caller owns the transaction, so a route or a job can combine several operations
(store a result and its violation events, say) atomically. A frame's events are written with its result
(service.frames.repository.record_frame_outcomes), so a recomputed frame replaces them instead of counting twice.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, cast

from sqlalchemy import Table, func, select
from sqlalchemy.orm import Session

from service.domain import ViolationIn
from service.store.models import Frame, ViolationEvent, finite_or_none

MINUTE_S = 60
HOUR_S = 3600

_VIOLATION_EVENTS = cast(Table, ViolationEvent.__table__)


@dataclass(frozen=True)
class ViolationBucket:
    """Violations whose timestamp falls in [start, start + width)."""

    start: datetime
    count: int


def violation_rows(
    camera_id: str, frame_id: uuid.UUID, timestamp: datetime, violations: Sequence[ViolationIn]
) -> list[dict[str, Any]]:
    epoch_s = math.floor(timestamp.timestamp())
    rows = []
    for v in violations:
        i, j = sorted((int(v.person_i), int(v.person_j)))
        if i == j or i < 0:
            raise ValueError(f"a violation needs two different people, got ({v.person_i}, {v.person_j})")
        rows.append(
            {
                "camera_id": camera_id,
                "frame_id": frame_id,
                "timestamp": timestamp,
                "epoch_s": epoch_s,
                "person_i": i,
                "person_j": j,
                "distance_m": float(v.distance_m),
                "distance_std_m": finite_or_none(v.distance_std_m),
            }
        )
    return rows


@dataclass(frozen=True)
class ViolationPlace:
    """A violation event with where its two people stood on the ground (metres, the frame result's `ground_m`)."""

    timestamp: datetime
    ground_i_m: tuple[float, float]
    ground_j_m: tuple[float, float]


def violation_places(
    session: Session, camera_id: str, *, since: datetime, until: datetime, limit: int
) -> list[ViolationPlace]:
    """The newest `limit` violation events in [since, until) with their people's ground positions.

    Positions come from the frames' stored results (one read per frame, not per event); an event whose frame
    has no position for either person (re-measured meanwhile, say) is left out.
    """
    events = session.execute(
        select(ViolationEvent.frame_id, ViolationEvent.timestamp, ViolationEvent.person_i, ViolationEvent.person_j)
        .where(
            ViolationEvent.camera_id == camera_id,
            ViolationEvent.epoch_s >= math.floor(since.timestamp()),
            ViolationEvent.epoch_s < math.floor(until.timestamp()),
        )
        .order_by(ViolationEvent.epoch_s.desc(), ViolationEvent.id.desc())
        .limit(limit)
    ).all()
    positions: dict[uuid.UUID, dict[int, tuple[float, float]]] = {}
    frame_ids = list({event.frame_id for event in events})
    for start in range(0, len(frame_ids), 500):
        chunk = frame_ids[start : start + 500]
        for frame_id, result in session.execute(select(Frame.id, Frame.result).where(Frame.id.in_(chunk))):
            people = (result or {}).get("people", [])
            positions[frame_id] = {
                p["index"]: (float(p["ground_m"][0]), float(p["ground_m"][1])) for p in people if p.get("ground_m")
            }
    places = []
    for event in events:
        placed = positions.get(event.frame_id, {})
        if event.person_i in placed and event.person_j in placed:
            places.append(ViolationPlace(event.timestamp, placed[event.person_i], placed[event.person_j]))
    return places


def violation_counts(
    session: Session,
    camera_id: str,
    *,
    since: datetime,
    until: datetime | None = None,
    bucket_s: int = MINUTE_S,
) -> list[ViolationBucket]:
    """Violation counts per time bucket (UTC-aligned, `bucket_s` wide) from `since`, empty buckets omitted.

    Buckets are integer arithmetic on epoch seconds, `epoch_s / width * width` (integer division on both
    backends), grouped in an outer query so PostgreSQL sees one grouping column rather than two textually
    different parameterised expressions. Resolution is one second: `since` and `until` are floored to whole
    seconds, `until` exclusive.
    """
    if bucket_s < 1:
        raise ValueError(f"bucket_s must be positive, got {bucket_s}")
    conditions = [ViolationEvent.camera_id == camera_id, ViolationEvent.epoch_s >= math.floor(since.timestamp())]
    if until is not None:
        conditions.append(ViolationEvent.epoch_s < math.floor(until.timestamp()))
    buckets = select(((ViolationEvent.epoch_s // bucket_s) * bucket_s).label("bucket")).where(*conditions).subquery()
    stmt = select(buckets.c.bucket, func.count()).group_by(buckets.c.bucket).order_by(buckets.c.bucket)
    return [
        ViolationBucket(start=datetime.fromtimestamp(int(bucket), UTC), count=int(count))
        for bucket, count in session.execute(stmt)
    ]
