"""A measuring job's chunk isolates its frames: a result the store cannot take fails its own frame, and every other
frame of the chunk is stored once, with its violation events and webhook events once (issue 14).

Junk results are injected where the measuring job hands a chunk to the store (service.frames.service.store_outcomes):
a violation pairing a person with themself, an unknown status. The geometry does not produce them today; the point is
that if anything ever does, the camera's other frames are not held back (a chunk that always failed failed every
retry of its job).
"""

from __future__ import annotations

import itertools
import uuid
from collections import Counter
from datetime import UTC, datetime, timedelta
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from service.cameras.repository import upsert_camera
from service.domain import FrameOutcome, PersonIn, ViolationIn
from service.frames.ingest import add_keypoint_frame
from service.frames.service import store_outcomes
from service.settings import get_settings
from service.store.models import Camera, Frame, ViolationEvent
from service.store.webhook_models import WebhookEvent
from service.webhooks.repository import create_subscription
from service.webhooks.signing import generate_secret

T0 = datetime(2026, 3, 1, 9, 0, tzinfo=UTC)
# Frames of every example stand somewhere new: the cooldown (kept in the test's database across examples) must
# not silence a pair because an earlier example alerted there.
_places = itertools.count()


def _setup(sessions: sessionmaker[Session]) -> Camera:
    with sessions() as session, session.begin():
        camera = session.get(Camera, "cam-m")
        if camera is None:
            camera, _ = upsert_camera(session, "cam-m", image_width_px=1920, image_height_px=1080, person_height_m=1.7)
            create_subscription(
                session,
                url="https://hooks.example.com/x",
                secret=generate_secret(),
                event_types=["violation.detected"],
                camera_ids=None,
            )
    return camera


def _pending_frames(sessions: sessionmaker[Session], n: int) -> list[Frame]:
    frames = []
    with sessions() as session, session.begin():
        for _ in range(n):
            people = [PersonIn((900.0, 400.0), (900.0, 700.0)), PersonIn((1000.0, 400.0), (1000.0, 700.0))]
            frame, _ = add_keypoint_frame(session, "cam-m", timestamp=T0, people=people)
            frames.append(frame)
    return frames


def _outcome(frame: Frame, k: int, kind: str) -> FrameOutcome:
    """A measured frame: its two people 0.5 m apart, somewhere of their own (so no cooldown joins two frames)."""
    result: dict[str, Any] = {
        "calibration_version": 1,
        "distance_threshold_m": 1.8288,
        "people": [
            {"index": 0, "placed_from": "ankles", "ground_m": [10.0 * k, 5.0], "point_m": None},
            {"index": 1, "placed_from": "ankles", "ground_m": [10.0 * k + 0.5, 5.0], "point_m": None},
        ],
        "pairs": [],
        "violations": [],
    }
    violations = [ViolationIn(0, 1, 0.5, 0.05, ground_i_m=(10.0 * k, 5.0), ground_j_m=(10.0 * k + 0.5, 5.0))]
    status = "done"
    if kind == "a person paired with themself":
        violations = [ViolationIn(1, 1, 0.0, ground_i_m=(10.0 * k + 0.5, 5.0), ground_j_m=(10.0 * k + 0.5, 5.0))]
    elif kind == "an unknown status":
        status = "measured"
    timestamp = T0 + timedelta(seconds=k)
    return FrameOutcome(frame.id, frame.camera_id, timestamp, status, 1, result=result, violations=violations)


JUNK = ["a person paired with themself", "an unknown status"]


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.sampled_from(["valid", "valid", *JUNK]), min_size=1, max_size=8))
def test_any_junk_result_fails_alone_and_every_other_frame_is_stored_once(
    sessions: sessionmaker[Session], kinds: list[str]
) -> None:
    camera = _setup(sessions)
    frames = _pending_frames(sessions, len(kinds))
    outcomes = [_outcome(frame, next(_places), kind) for frame, kind in zip(frames, kinds, strict=True)]
    client_ids: dict[uuid.UUID, str | None] = {frame.id: None for frame in frames}

    stored, deliveries = store_outcomes(get_settings(), camera, outcomes, client_ids)

    assert [o.status for o in stored] == ["done" if kind == "valid" else "failed" for kind in kinds]
    valid = [frame.id for frame, kind in zip(frames, kinds, strict=True) if kind == "valid"]
    with sessions() as session:
        status = dict(session.execute(select(Frame.id, Frame.status).where(Frame.id.in_([f.id for f in frames]))).all())
        errors = dict(session.execute(select(Frame.id, Frame.error).where(Frame.id.in_([f.id for f in frames]))).all())
        events = Counter(
            session.scalars(select(ViolationEvent.frame_id).where(ViolationEvent.frame_id.in_([f.id for f in frames])))
        )
        webhook_events = session.scalar(
            select(func.count())
            .select_from(WebhookEvent)
            .where(WebhookEvent.dedupe_key.in_([f"violation:{frame_id}" for frame_id in valid]))
        )
    for frame, kind in zip(frames, kinds, strict=True):
        if kind == "valid":
            assert status[frame.id] == "done" and events[frame.id] == 1 and errors[frame.id] is None
        else:
            assert status[frame.id] == "failed" and events[frame.id] == 0
            assert "could not be stored" in (errors[frame.id] or "")
    assert webhook_events == len(valid) == len(deliveries)
