"""A write batch isolates its frames: whatever junk shares a batch with valid frames, every valid frame is stored
exactly once and each junk frame gets its own error (issue 14).

Junk here is what validation must stop but the store must survive anyway: a number float32 cannot hold (the
issue's 1e39), a non-finite centre, a naive timestamp, a camera deleted or resized since it was read.
"""

from __future__ import annotations

import uuid
from collections import Counter
from datetime import datetime
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session, sessionmaker

from service.cameras.repository import CameraNotFoundError, CameraResizedError
from service.domain import PersonIn
from service.frames.ingest import FramesRefusedError, NewKeypointFrame, add_keypoint_frames, prepare_keypoint_frame
from service.frames.writer import FrameNotStorableError, FrameWriter
from service.store import make_session_factory
from service.store.models import Camera, Frame, Observation
from tests.support.store import SIZE_PX, T0, add_camera, person_at

pytestmark = pytest.mark.both_backends

COCO_ROW = [[400.0, 300.0 + 10 * k, 0.9] for k in range(17)]


def _cameras(factory: sessionmaker[Session]) -> tuple[Camera, Camera]:
    with factory() as session:
        cameras = add_camera(session, "cam-1"), add_camera(session, "cam-2")
        session.commit()
    return cameras


def _junk(kind: str, camera: Camera) -> tuple[NewKeypointFrame, type[Exception]]:
    """A frame of `kind` and the error it must get."""
    if kind == "float32 overflow":
        keypoints = [list(row) for row in COCO_ROW]
        keypoints[0] = [1e39, 0.0, 0.0]
        return NewKeypointFrame(camera, T0, [PersonIn(None, None, keypoints=keypoints)]), FrameNotStorableError
    if kind == "non-finite centre":
        return NewKeypointFrame(camera, T0, [PersonIn((float("nan"), 10.0), (5.0, 90.0))]), FrameNotStorableError
    if kind == "naive timestamp":
        return NewKeypointFrame(camera, datetime(2024, 5, 1), [person_at(100, 400)]), FrameNotStorableError
    if kind == "deleted camera":
        gone = Camera(id="gone", image_width_px=SIZE_PX, image_height_px=SIZE_PX)
        return NewKeypointFrame(gone, T0, [person_at(100, 400)]), CameraNotFoundError
    assert kind == "resized camera"
    stale = Camera(id=camera.id, image_width_px=SIZE_PX * 2, image_height_px=SIZE_PX)
    return NewKeypointFrame(stale, T0, [person_at(100, 400)]), CameraResizedError


JUNK = ["float32 overflow", "non-finite centre", "naive timestamp", "deleted camera", "resized camera"]
valid_frame = st.tuples(st.integers(0, 1), st.integers(0, 4), st.booleans())  # camera, people, has a client id
batch = st.tuples(
    st.lists(valid_frame, max_size=12),
    st.lists(st.tuples(st.sampled_from(JUNK), st.integers(0, 1)), max_size=5),
    st.lists(st.integers(0, 11), max_size=3),  # retries of valid frames in the same batch
    st.randoms(use_true_random=False),
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(batch)
def test_any_junk_in_a_batch_leaves_every_valid_frame_stored_exactly_once(engine: Engine, drawn: Any) -> None:
    valid_specs, junk_specs, retries, rng = drawn
    factory = make_session_factory(engine)
    with factory() as session:
        cameras = tuple(session.get(Camera, c) for c in ("cam-1", "cam-2"))
    if None in cameras:
        cameras = _cameras(factory)
    run = uuid.uuid4().hex[:8]
    valid: list[NewKeypointFrame] = []
    for k, (camera, people, has_id) in enumerate(valid_specs):
        client_id = f"{run}-{k}" if has_id else None
        valid.append(
            NewKeypointFrame(cameras[camera], T0, [person_at(100 + 60 * i, 400) for i in range(people)], client_id)
        )
    repeated = [valid[k] for k in retries if k < len(valid) and valid[k].client_frame_id is not None]
    junk = [_junk(kind, cameras[camera]) for kind, camera in junk_specs]
    frames = [(frame, None) for frame in [*valid, *repeated]] + list(junk)
    rng.shuffle(frames)

    with factory() as session:
        evidence_before = {c.id: c.usable_evidence_count for c in session.scalars(select(Camera))}
    answers = FrameWriter(factory).store_batch([frame for frame, _ in frames])

    created: Counter[uuid.UUID] = Counter()
    for (frame, error), answer in zip(frames, answers, strict=True):
        if error is not None:
            assert isinstance(answer, error), (frame, answer)
        else:
            assert isinstance(answer, tuple), (frame, answer)
            stored, was_created = answer
            created[stored.id] += was_created
            assert stored.people == len(frame.people)
    assert set(created.values()) <= {1}
    with factory() as session:
        ids = list(created)
        rows = dict(
            session.execute(
                select(Observation.frame_id, func.count()).where(Observation.frame_id.in_(ids)).group_by("frame_id")
            ).all()
        )
        client_ids = Counter(
            session.scalars(select(Frame.client_frame_id).where(Frame.client_frame_id.like(f"{run}-%")))
        )
        evidence_after = {c.id: c.usable_evidence_count for c in session.scalars(select(Camera))}
    assert sum(created.values()) == len(valid)  # every valid frame, once, and no junk
    assert client_ids == Counter(f.client_frame_id for f in valid if f.client_frame_id is not None)
    assert sum(rows.values()) == sum(len(f.people) for f in valid)
    for camera in cameras:
        added = sum(len(f.people) for f in valid if f.camera.id == camera.id)
        assert evidence_after[camera.id] - evidence_before[camera.id] == added


def test_frames_of_a_resized_or_deleted_camera_are_refused_before_anything_is_written(engine: Engine) -> None:
    factory = make_session_factory(engine)
    one, _ = _cameras(factory)
    stale = Camera(id="cam-1", image_width_px=640, image_height_px=480)
    frames = [
        NewKeypointFrame(one, T0, [person_at(100, 400)]),
        NewKeypointFrame(stale, T0, [person_at(100, 400)]),
        NewKeypointFrame(Camera(id="gone", image_width_px=1, image_height_px=1), T0, []),
    ]
    with factory() as session:
        try:
            add_keypoint_frames(session, [prepare_keypoint_frame(item, received_at=T0) for item in frames])
        except FramesRefusedError as refused:
            errors = refused.errors
        else:
            raise AssertionError("stale frames were stored")
        assert session.scalar(select(func.count()).select_from(Frame)) == 0
    assert set(errors) == {1, 2}
    assert isinstance(errors[1], CameraResizedError) and errors[1].size_px == (SIZE_PX, SIZE_PX)
    assert isinstance(errors[2], CameraNotFoundError)
