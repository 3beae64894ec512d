"""Frames and their people in the store, on SQLite and PostgreSQL."""

from __future__ import annotations

import json
import math
import threading
import uuid
from datetime import datetime, timedelta
from typing import Any

import pytest
from sqlalchemy import Engine
from sqlalchemy.orm import Session

from service.calibration.repository import reset_calibration
from service.cameras.repository import CameraNotFoundError
from service.domain import FrameOutcome, PersonIn
from service.frames import ingest
from service.frames.ingest import add_image_frame, add_keypoint_frame, record_detections
from service.frames.keypoints import BOX_REASON, PARTIAL_REASON, SEATED_REASON, as_static
from service.frames.measure import measure_people
from service.frames.repository import (
    frame_observations,
    frames_points,
    get_frame,
    pending_frames,
    record_frame_outcomes,
    seen_people_boxes,
)
from service.store import make_session_factory
from service.store.models import Frame, Observation
from tests.render.scenes import calibration_of, tilted_scene
from tests.support.store import (
    GRID_COLS,
    SIZE_PX,
    T0,
    add_camera,
    add_frame,
    count,
    evidence_count,
    person_at,
    person_in_cell,
)

pytestmark = pytest.mark.both_backends
Box = tuple[float, float, float, float]


def test_add_keypoint_frame_stores_people_and_counts_usable_evidence(session: Session) -> None:
    add_camera(session)
    keypoints = [[float(i), float(i) + 0.5, 0.9] for i in range(17)]
    people = [
        person_at(150.0, 750.0, keypoints=keypoints),
        PersonIn(shoulder_px=(10.0, 10.0), ankle_px=None),
        person_at(805.0, -3.0, unusable_reason="low keypoint scores"),
        person_at(400.0, 400.0, unusable_reason="why " * 60),  # longer than the column: cut, on both backends
    ]
    received = T0 + timedelta(seconds=2)
    frame, created = add_keypoint_frame(session, "cam-1", timestamp=T0, people=people, received_at=received)
    session.commit()
    assert created
    assert (frame.status, frame.source, frame.people, frame.result) == ("pending", "keypoints", 4, None)
    assert (frame.timestamp, frame.received_at) == (T0, received)

    observations = frame_observations(session, frame.id)
    assert [o.person_index for o in observations] == [0, 1, 2, 3]
    first, no_ankle, low_score, verbose = observations
    assert verbose.unusable_reason == ("why " * 60)[:197] + "..."
    assert first.usable and first.unusable_reason is None
    assert (first.ankle_x_px, first.ankle_y_px, first.shoulder_y_px) == (150.0, 750.0, 690.0)
    assert first.cell == 7 * GRID_COLS + 1
    assert first.keypoints == keypoints
    assert not no_ankle.usable and no_ankle.unusable_reason == "ankle centre not visible"
    assert no_ankle.cell is None and no_ankle.ankle_x_px is None
    assert not low_score.usable and low_score.unusable_reason == "low keypoint scores"
    assert low_score.cell == GRID_COLS - 1  # outside the image: clamped to the edge cell
    assert evidence_count(session, "cam-1") == 1
    assert count(session, Observation, camera_id="cam-1", usable=True) == 1


def test_a_retry_with_the_same_client_frame_id_is_the_same_frame(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    people = [person_in_cell(3), person_in_cell(4)]
    first, created = add_keypoint_frame(session, "cam-1", timestamp=T0, people=people, client_frame_id="f-1")
    session.commit()
    retry, created_again = add_keypoint_frame(session, "cam-1", timestamp=T0, people=people, client_frame_id="f-1")
    session.commit()
    other, created_other = add_keypoint_frame(session, "cam-2", timestamp=T0, people=people, client_frame_id="f-1")
    session.commit()
    assert created and not created_again and created_other
    assert retry.id == first.id and other.id != first.id
    assert count(session, Frame, camera_id="cam-1") == 1
    assert count(session, Observation, camera_id="cam-1") == 2
    assert evidence_count(session, "cam-1") == 2


def test_frames_without_a_client_id_never_collide(session: Session) -> None:
    add_camera(session)
    ids = {add_frame(session, "cam-1", [person_in_cell(0)]).id for _ in range(3)}
    session.commit()
    assert len(ids) == 3
    assert evidence_count(session, "cam-1") == 3


def test_a_retry_that_loses_the_race_returns_the_winners_frame(
    session: Session, engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The pre-check missed the frame (another process committed it in between): the unique constraint decides."""
    add_camera(session)
    session.commit()
    with make_session_factory(engine)() as other:
        winner, _ = add_keypoint_frame(other, "cam-1", timestamp=T0, people=[person_in_cell(0)], client_frame_id="f-1")
        other.commit()

    real_lookup = ingest._frame_by_client_id
    calls = []

    def stale_first_lookup(*args: Any) -> Frame | None:
        calls.append(args)
        return None if len(calls) == 1 else real_lookup(*args)

    monkeypatch.setattr(ingest, "_frame_by_client_id", stale_first_lookup)
    frame, created = add_keypoint_frame(
        session, "cam-1", timestamp=T0, people=[person_in_cell(0)], client_frame_id="f-1"
    )
    session.commit()
    assert not created and frame.id == winner.id and len(calls) == 2
    assert count(session, Observation, camera_id="cam-1") == 1
    assert evidence_count(session, "cam-1") == 1


def test_concurrent_retries_store_one_frame(session: Session, engine: Engine) -> None:
    add_camera(session)
    session.commit()
    factory = make_session_factory(engine)
    barrier = threading.Barrier(4)
    outcomes: list[tuple[uuid.UUID, bool]] = []
    errors: list[BaseException] = []

    def post() -> None:
        try:
            with factory() as own:
                barrier.wait()
                frame, created = add_keypoint_frame(
                    own, "cam-1", timestamp=T0, people=[person_in_cell(5)] * 3, client_frame_id="same"
                )
                own.commit()
                outcomes.append((frame.id, created))
        except BaseException as exc:  # surfaced below: a thread's exception would otherwise vanish
            errors.append(exc)

    threads = [threading.Thread(target=post) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=30)
    assert not errors, errors
    assert len({frame_id for frame_id, _ in outcomes}) == 1
    assert sorted(created for _, created in outcomes) == [False, False, False, True]
    session.expire_all()
    assert count(session, Observation, camera_id="cam-1") == 3
    assert evidence_count(session, "cam-1") == 3


def test_frames_need_a_known_camera_aware_timestamps_and_finite_points(session: Session) -> None:
    with pytest.raises(CameraNotFoundError):
        add_keypoint_frame(session, "nope", timestamp=T0, people=[])
    add_camera(session)
    with pytest.raises(ValueError, match="finite"):
        add_keypoint_frame(
            session, "cam-1", timestamp=T0, people=[PersonIn(shoulder_px=(math.nan, 1.0), ankle_px=(1.0, 2.0))]
        )
    with pytest.raises(ValueError, match="timezone"):
        add_keypoint_frame(session, "cam-1", timestamp=datetime(2024, 1, 1), people=[])


def test_pending_frames_results_and_scoping(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    late = add_frame(session, "cam-1", [], at=T0)
    early = add_frame(session, "cam-1", [], at=T0)
    late.received_at, early.received_at = T0 + timedelta(seconds=5), T0 + timedelta(seconds=1)
    elsewhere = add_frame(session, "cam-2", [])
    elsewhere.received_at = T0 + timedelta(seconds=3)
    session.commit()
    assert [f.id for f in pending_frames(session, "cam-1")] == [early.id, late.id]
    assert [f.id for f in pending_frames(session)] == [early.id, elsewhere.id, late.id]
    assert [f.id for f in pending_frames(session, limit=1)] == [early.id]

    result = {"people": [{"position_m": [1.0, 2.0]}], "pairs": [{"i": 0, "j": 1, "distance_m": 1.5}]}
    done = FrameOutcome(early.id, "cam-1", early.timestamp, "done", 3, result=result)
    assert record_frame_outcomes(session, [done]) == 1
    session.commit()
    session.expire_all()
    fetched = get_frame(session, "cam-1", early.id)
    assert fetched is not None and fetched.processed_at is not None
    assert (fetched.status, fetched.result, fetched.calibration_version) == ("done", result, 3)
    assert get_frame(session, "cam-2", early.id) is None  # a frame id does not cross cameras
    assert [f.id for f in pending_frames(session, "cam-1")] == [late.id]

    failed = FrameOutcome(late.id, "cam-1", late.timestamp, "failed", 3, error="no calibration")
    record_frame_outcomes(session, [failed])
    session.expire_all()
    fetched = get_frame(session, "cam-1", late.id)
    assert fetched is not None and (fetched.status, fetched.error) == ("failed", "no calibration")
    with pytest.raises(ValueError, match="done or failed"):
        record_frame_outcomes(session, [FrameOutcome(late.id, "cam-1", late.timestamp, "exploded", 3)])
    gone = FrameOutcome(uuid.uuid4(), "cam-1", late.timestamp, "done", 3, result=result)
    assert record_frame_outcomes(session, [gone]) == 0  # a frame deleted meanwhile is simply not updated


def test_seen_people_boxes_are_the_usable_people_of_the_latest_image_frames(session: Session) -> None:
    """What sizes an uncalibrated camera's next search: the boxes of the whole standing people of its latest image
    frames whose people are stored, in its current epoch; not older frames, not people who are not evidence, not
    frames still waiting for their pose, not posted keypoints (no boxes) and not another camera's."""
    camera = add_camera(session, "cam-1")
    cameras = {"cam-1": camera, "cam-2": add_camera(session, "cam-2")}

    def image_frame(camera_id: str, second: int, boxes: list[Box], *, usable: bool = True) -> None:
        frame, _ = add_image_frame(
            session,
            cameras[camera_id],
            timestamp=T0 + timedelta(seconds=second),
            content_type="image/jpeg",
            width_px=SIZE_PX,
            height_px=SIZE_PX,
            data=b"jpeg",
        )
        people = [
            person_at((box[0] + box[2]) / 2, box[3], box_px=box, unusable_reason=None if usable else "seated")
            for box in boxes
        ]
        if people:
            assert record_detections(session, frame.id, people, pose_model="test") is not None

    def box(k: int) -> Box:
        return (10.0 * k, 100.0, 10.0 * k + 5, 200.0)

    image_frame("cam-1", 0, [box(0)])  # the oldest: one frame too many
    for second in (1, 2, 3):
        image_frame("cam-1", second, [box(second), box(10 + second)])
    image_frame("cam-1", 4, [box(4)], usable=False)  # seated people
    image_frame("cam-1", 5, [])  # still waiting for its pose: not one of the latest
    add_frame(session, "cam-1", [person_at(50.0, 60.0)], at=T0 + timedelta(seconds=6))  # posted keypoints
    image_frame("cam-2", 7, [box(7)])
    session.commit()

    seen = sorted(seen_people_boxes(session, "cam-1", camera.epoch, frames=4))
    assert seen == sorted([box(k) for k in (1, 2, 3, 11, 12, 13)])
    assert len(seen_people_boxes(session, "cam-1", camera.epoch, frames=5)) == 7
    assert seen_people_boxes(session, "cam-2", 1, frames=5) == [box(7)]

    reset_calibration(session, "cam-1", drop_evidence=False)  # a new epoch: the old view's people say nothing
    session.commit()
    session.refresh(camera)
    assert seen_people_boxes(session, "cam-1", camera.epoch, frames=5) == []


def test_what_measuring_reads_of_a_verdict_is_stored_with_each_person(session: Session) -> None:
    """Posture, a box-bottom contact and a static spot survive the store, so a stored frame is measured as the
    people were found; a static person placed from their box fits the reason column (PostgreSQL refused its
    202-character reason when measuring read these from how the reason began)."""
    camera = add_camera(session, "cam-1")
    frame, _ = add_image_frame(
        session, camera, timestamp=T0, content_type="image/jpeg", width_px=SIZE_PX, height_px=SIZE_PX, data=b"jpeg"
    )
    box = (380.0, 300.0, 420.0, 500.0)
    people = [
        person_at(100.0, 600.0, box_px=box, posture="standing"),
        PersonIn((300.0, 500.0), None, unusable_reason=SEATED_REASON, box_px=box, posture="seated"),
        PersonIn((500.0, 420.0), None, unusable_reason=PARTIAL_REASON, box_px=box, posture="partial"),
        PersonIn(None, (600.0, 640.0), unusable_reason=BOX_REASON, box_px=box, posture="unknown", placed_from_box=True),
        as_static(PersonIn(None, (700.0, 660.0), unusable_reason=BOX_REASON, box_px=box, placed_from_box=True)),
        as_static(person_at(200.0, 700.0, box_px=box, posture="seated")),
    ]
    assert record_detections(session, frame.id, people, pose_model="test") is not None
    session.commit()
    rows = frames_points(session, [frame.id])[frame.id]
    assert [(r.posture, r.placed_from_box, r.static) for r in rows] == [
        ("standing", False, False),
        ("seated", False, False),
        ("partial", False, False),
        ("unknown", True, False),
        (None, True, True),
        ("seated", False, True),
    ]
    assert [r.usable for r in rows] == [True] + [False] * 5
    cal = calibration_of(tilted_scene(n_people=4))
    stored = measure_people(rows, cal, distance_threshold_m=10.0)
    assert stored.result_json() == measure_people(people, cal, distance_threshold_m=10.0).result_json()
    placed = json.loads(stored.result_json())["people"]
    assert [p["placed_from"] for p in placed] == ["ankles", "shoulders", "shoulders", "box", "box", "ankles"]
    assert [p["static"] for p in placed] == [False] * 4 + [True] * 2
