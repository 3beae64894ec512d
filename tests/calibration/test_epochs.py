"""Calibration epochs in the store, on SQLite and PostgreSQL: what a detected move does to a camera's people,
frames, versions and counters."""

from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy.orm import Session

from service.calibration.evidence import sample_evidence
from service.calibration.repository import (
    add_calibration,
    current_calibration,
    movement_state,
    open_epoch_after_move,
    save_movement_state,
)
from service.cameras.repository import get_camera
from service.domain import ViolationIn
from service.store.models import Frame, Observation, ViolationEvent
from tests.support.store import T0, add_camera, add_frame, count, key_everyone, ok_values, person_at, record_violations

pytestmark = pytest.mark.both_backends


def test_a_move_opens_the_next_epoch_with_the_frames_of_the_new_view(session: Session) -> None:
    add_camera(session)
    frames = [
        add_frame(
            session, "cam-1", [person_at(400.0 + k, 800.0), person_at(900.0, 700.0)], at=T0 + timedelta(seconds=k)
        )
        for k in range(6)
    ]
    version = add_calibration(session, "cam-1", ok_values(evidence_count=12), make_current=True)
    for frame in frames:
        record_violations(session, frame, [ViolationIn(0, 1, 1.0, 0.1)])
    save_movement_state(session, "cam-1", epoch=1, calibration_version=version.version, state=b"x", statistic=1.0)
    session.commit()

    moved_at = frames[4].timestamp
    assert open_epoch_after_move(session, "cam-1", from_epoch=1, moved_at=moved_at)
    session.commit()
    assert not open_epoch_after_move(session, "cam-1", from_epoch=1, moved_at=moved_at)  # already closed

    camera = get_camera(session, "cam-1")
    assert camera is not None
    assert (camera.epoch, camera.epoch_reason, camera.moved_at, camera.moves) == (2, "camera_moved", moved_at, 1)
    assert camera.usable_evidence_count == 4 and camera.evidence_at_last_solve == 0  # two frames of two people
    assert current_calibration(session, "cam-1") is None and movement_state(session, "cam-1") is None
    session.expire_all()
    statuses = {f.id: (f.status, f.calibration_version) for f in session.query(Frame).all()}
    assert [statuses[f.id] for f in frames] == [("done", 1)] * 4 + [("pending", None)] * 2
    assert count(session, ViolationEvent, camera_id="cam-1") == 4
    assert count(session, Observation, camera_id="cam-1", epoch=1) == 8
    assert count(session, Observation, camera_id="cam-1", epoch=2) == 4
    key_everyone(session, "cam-1")
    assert len(sample_evidence(session, "cam-1", cap=100)) == 4
    # People posted from now on join the new epoch; a solve of the old one is kept but never made current.
    add_frame(session, "cam-1", [person_at(500.0, 900.0)], at=T0 + timedelta(seconds=10))
    assert count(session, Observation, camera_id="cam-1", epoch=2) == 5
    stale = add_calibration(session, "cam-1", ok_values(evidence_count=12), make_current=True, epoch=1)
    assert not stale.is_current and stale.epoch == 1
    fresh = add_calibration(session, "cam-1", ok_values(evidence_count=5), make_current=True)
    assert fresh.is_current and fresh.epoch == 2
