"""Violation events in the store, on SQLite and PostgreSQL."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.domain import ViolationIn
from service.store.models import ViolationEvent
from service.violations.repository import HOUR_S, ViolationBucket, violation_counts
from tests.support.store import T0, add_camera, add_frame, count, person_in_cell, record_violations

pytestmark = pytest.mark.both_backends


def test_recording_violations_replaces_the_frames_previous_events(session: Session) -> None:
    add_camera(session)
    frame = add_frame(session, "cam-1", [person_in_cell(0)] * 3)
    record_violations(session, frame, [ViolationIn(0, 1, 1.1, 0.1), ViolationIn(2, 0, 0.9)])
    session.commit()
    pairs = session.execute(select(ViolationEvent.person_i, ViolationEvent.person_j).order_by(ViolationEvent.id))
    assert [tuple(p) for p in pairs] == [(0, 1), (0, 2)]

    record_violations(session, frame, [ViolationIn(1, 2, 1.0)])
    session.commit()
    assert count(session, ViolationEvent, frame_id=frame.id) == 1
    with pytest.raises(ValueError, match="two different people"):
        record_violations(session, frame, [ViolationIn(1, 1, 0.0)])


def test_violation_counts_per_minute_and_hour(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    events = [  # (seconds after 10:00, violations in that frame)
        (5.5, 2),
        (59.9, 1),
        (60.0, 1),
        (3599.0, 1),
        (3600.0, 3),
    ]
    for offset_s, n in events:
        frame = add_frame(session, "cam-1", [person_in_cell(0)] * (n + 1), at=T0 + timedelta(seconds=offset_s))
        record_violations(session, frame, [ViolationIn(0, k + 1, 1.0) for k in range(n)])
    noise = add_frame(session, "cam-2", [person_in_cell(0)] * 6, at=T0 + timedelta(seconds=10))
    record_violations(session, noise, [ViolationIn(0, k + 1, 1.0) for k in range(5)])
    session.commit()

    def minute(m: int) -> datetime:
        return T0 + timedelta(minutes=m)

    assert violation_counts(session, "cam-1", since=T0) == [
        ViolationBucket(minute(0), 3),
        ViolationBucket(minute(1), 1),
        ViolationBucket(minute(59), 1),
        ViolationBucket(minute(60), 3),
    ]
    assert violation_counts(session, "cam-1", since=T0, bucket_s=HOUR_S) == [
        ViolationBucket(T0, 5),
        ViolationBucket(T0 + timedelta(hours=1), 3),
    ]
    # since/until in another time zone mean the same instants; until is exclusive.
    plus_two = timezone(timedelta(hours=2))
    assert violation_counts(
        session, "cam-1", since=minute(1).astimezone(plus_two), until=minute(60).astimezone(plus_two)
    ) == [ViolationBucket(minute(1), 1), ViolationBucket(minute(59), 1)]
    assert violation_counts(session, "cam-1", since=T0 + timedelta(days=1)) == []
    assert violation_counts(session, "cam-1", since=T0)[0].start.tzinfo is UTC
