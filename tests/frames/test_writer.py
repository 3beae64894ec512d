"""Group commit of posted frames: batches, retries within and across batches, and one answer per frame."""

from __future__ import annotations

import threading
import uuid
from collections import Counter
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime

import pytest
from sqlalchemy import Engine, delete, select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from service.cameras.repository import CameraNotFoundError
from service.domain import CameraCounters
from service.frames import writer as frame_writer
from service.frames.ingest import NewKeypointFrame, PreparedKeypointFrame, add_keypoint_frames, prepare_keypoint_frame
from service.frames.repository import frame_observations
from service.frames.writer import FrameNotStorableError, FrameWriter
from service.store import make_session_factory
from service.store.models import Camera, Frame, Observation, utc_now
from tests.support.store import T0, add_camera, count, person_at

pytestmark = pytest.mark.both_backends


@pytest.fixture
def factory(engine: Engine) -> sessionmaker[Session]:
    return make_session_factory(engine)


def camera(factory: sessionmaker[Session], camera_id: str = "cam-1") -> Camera:
    with factory() as session:
        stored = add_camera(session, camera_id)
        session.commit()
    return stored


def frame(cam: Camera, client_frame_id: str | None = None, people: int = 2) -> NewKeypointFrame:
    return NewKeypointFrame(cam, T0, [person_at(100 + 50 * i, 400) for i in range(people)], client_frame_id)


def store(session: Session, frames: Sequence[NewKeypointFrame]) -> list[tuple[Frame, bool]]:
    received_at = utc_now()
    return add_keypoint_frames(session, [prepare_keypoint_frame(item, received_at=received_at) for item in frames])


def test_a_client_id_stored_on_one_camera_is_new_on_another_in_one_batch(factory: sessionmaker[Session]) -> None:
    """The stored-id lookup crosses the batch's cameras with its client ids: cam-1's stored "a" must not make
    cam-2's "a" a retry, nor cam-1's "b" one of cam-2's stored "b"."""
    one, two = camera(factory, "cam-1"), camera(factory, "cam-2")
    with factory() as session:
        first = store(session, [frame(one, "a"), frame(two, "b")])
        session.commit()
    with factory() as session:
        stored = store(session, [frame(two, "a"), frame(one, "b"), frame(one, "a")])
        session.commit()
    assert [created for _, created in stored] == [True, True, False]
    assert stored[2][0].id == first[0][0].id
    with factory() as session:
        assert count(session, Frame) == 4


def test_batch_stores_every_frame_and_counts_evidence(factory: sessionmaker[Session]) -> None:
    one, two = camera(factory, "cam-1"), camera(factory, "cam-2")
    with factory() as session:
        stored = store(session, [frame(one), frame(two, people=3), frame(one, people=1)])
        session.commit()
    assert [created for _, created in stored] == [True, True, True]
    assert [f.people for f, _ in stored] == [2, 3, 1]
    with factory() as session:
        assert count(session, Frame) == 3 and count(session, Observation) == 6
        assert session.get(Camera, "cam-1").usable_evidence_count == 3  # type: ignore[union-attr]
        assert session.get(Camera, "cam-2").usable_evidence_count == 3  # type: ignore[union-attr]
        # Each frame's people are its own, in posted order.
        for stored_frame, _ in stored:
            indices = [o.person_index for o in frame_observations(session, stored_frame.id)]
            assert indices == list(range(stored_frame.people))


def test_batch_answers_retries_from_the_store_and_from_within_the_batch(factory: sessionmaker[Session]) -> None:
    cam = camera(factory)
    with factory() as session:
        ((first, _),) = store(session, [frame(cam, "a")])
        session.commit()
    with factory() as session:
        stored = store(session, [frame(cam, "a"), frame(cam, "b"), frame(cam, "b")])
        session.commit()
    assert [(f.id == first.id, created) for f, created in stored[:1]] == [(True, False)]
    assert stored[1][1] is True and stored[2] == (stored[1][0], False)
    with factory() as session:
        assert count(session, Frame) == 2 and count(session, Observation) == 4
        assert session.get(Camera, "cam-1").usable_evidence_count == 4  # type: ignore[union-attr]


def test_concurrent_posts_are_batched_and_each_answered(
    factory: sessionmaker[Session], monkeypatch: pytest.MonkeyPatch
) -> None:
    cam = camera(factory)
    writer = FrameWriter(factory)
    batches: list[int] = []

    def counting(
        session: Session, frames: list[PreparedKeypointFrame], counters: dict[str, CameraCounters] | None = None
    ) -> list[tuple[Frame, bool]]:
        batches.append(len(frames))
        return add_keypoint_frames(session, frames, counters)

    monkeypatch.setattr(frame_writer, "add_keypoint_frames", counting)
    # Client ids repeat (two retries of each frame), so some answers come from other threads' batches.
    items = [frame(cam, f"f-{i % 40}") for i in range(120)]
    with ThreadPoolExecutor(max_workers=16) as pool:
        answers = list(pool.map(writer.add, items))
    by_client: dict[str | None, set[uuid.UUID]] = {}
    for item, answer in zip(items, answers, strict=True):
        by_client.setdefault(item.client_frame_id, set()).add(answer.frame.id)
    assert all(len(ids) == 1 for ids in by_client.values())  # every retry got the same frame
    assert Counter(answer.created for answer in answers) == {True: 40, False: 80}
    assert sum(batches) == 120 and max(batches) > 1  # frames that queued together went in together
    with factory() as session:
        assert count(session, Frame) == 40 and count(session, Observation) == 80


def test_a_deleted_camera_fails_only_its_own_frames(factory: sessionmaker[Session]) -> None:
    kept, gone = camera(factory, "kept"), camera(factory, "gone")
    with factory() as session:
        session.execute(delete(Camera).where(Camera.id == "gone"))
        session.commit()
    # The foreign key refuses the batch as a whole; then each frame is stored on its own.
    answers = FrameWriter(factory).store_batch([frame(kept, "k-1"), frame(gone, "g-1"), frame(kept, "k-2")])
    assert isinstance(answers[1], CameraNotFoundError)
    assert [answer[1] for answer in (answers[0], answers[2])] == [True, True]  # type: ignore[index]
    with factory() as session:
        assert {f.client_frame_id for f in session.scalars(select(Frame))} == {"k-1", "k-2"}


def test_rows_are_built_before_the_transaction(
    factory: sessionmaker[Session], engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On SQLite a writing transaction holds the one write lock every other process waits for: a batch's rows are
    built while the writer holds no connection, and only the statements run inside."""
    cam = camera(factory)
    connections_held: list[int] = []

    def watched(item: NewKeypointFrame, *, received_at: datetime) -> PreparedKeypointFrame:
        connections_held.append(engine.pool.checkedout())  # type: ignore[attr-defined]
        return prepare_keypoint_frame(item, received_at=received_at)

    monkeypatch.setattr(frame_writer, "prepare_keypoint_frame", watched)
    answers = FrameWriter(factory).store_batch([frame(cam, "a"), frame(cam, "b", people=3)])
    assert connections_held == [0, 0]
    assert [answer[1] for answer in answers] == [True, True]  # type: ignore[index]


def test_a_frame_the_store_cannot_take_fails_alone(factory: sessionmaker[Session]) -> None:
    cam = camera(factory)
    unplaceable = NewKeypointFrame(cam, T0, [person_at(float("nan"), 400)], "bad")
    answers = FrameWriter(factory).store_batch([frame(cam, "a"), unplaceable, frame(cam, "b")])
    assert isinstance(answers[1], FrameNotStorableError)
    assert [answer[1] for answer in (answers[0], answers[2])] == [True, True]  # type: ignore[index]
    with factory() as session:
        assert {f.client_frame_id for f in session.scalars(select(Frame))} == {"a", "b"}


def test_a_failed_batch_fails_every_frame_in_it_and_no_waiter_hangs(factory: sessionmaker[Session]) -> None:
    cam = camera(factory)
    calls = 0

    def broken() -> Session:
        nonlocal calls
        calls += 1
        raise OperationalError("BEGIN", {}, Exception("database is unreachable"))

    writer = FrameWriter(broken)  # type: ignore[arg-type]
    with ThreadPoolExecutor(max_workers=8) as pool:
        futures = [pool.submit(writer.add, frame(cam)) for _ in range(16)]
        errors = [future.exception(timeout=30) for future in futures]
    assert all(isinstance(error, OperationalError) for error in errors)
    assert calls <= 16


def test_small_batches_still_reach_every_waiter(factory: sessionmaker[Session]) -> None:
    """With a batch cap smaller than the queue, the writer keeps taking batches until every frame is stored."""
    cam = camera(factory)
    writer = FrameWriter(factory, max_batch=2)
    start = threading.Barrier(12)

    def post(index: int) -> uuid.UUID:
        start.wait()
        answer = writer.add(frame(cam, f"s-{index}"))
        assert answer.created
        return answer.frame.id

    with ThreadPoolExecutor(max_workers=12) as pool:
        ids = list(pool.map(post, range(12)))
    assert len(set(ids)) == 12
    with factory() as session:
        assert count(session, Frame) == 12


def test_client_frame_ids_are_per_camera_within_one_batch(factory: sessionmaker[Session]) -> None:
    """One lookup answers retries of several cameras at once; the same client id on two cameras is two frames."""
    one, two, three = camera(factory, "cam-1"), camera(factory, "cam-2"), camera(factory, "cam-3")
    with factory() as session:
        first = store(session, [frame(one, "a"), frame(two, "b")])
        session.commit()
    with factory() as session:
        again = store(session, [frame(two, "b"), frame(one, "b"), frame(three, "a"), frame(one, "a")])
        session.commit()
    assert [created for _, created in again] == [False, True, True, False]
    assert again[0][0].id == first[1][0].id and again[3][0].id == first[0][0].id
    with factory() as session:
        assert count(session, Frame) == 4
        counts = {c.id: c.usable_evidence_count for c in session.query(Camera)}
        assert counts == {"cam-1": 4, "cam-2": 2, "cam-3": 2}  # two usable people per frame


def test_after_commit_sees_each_batch_once_and_its_errors_reach_their_frames(factory: sessionmaker[Session]) -> None:
    kept, gone = camera(factory, "kept"), camera(factory, "gone")
    with factory() as session:
        session.execute(delete(Camera).where(Camera.id == "gone"))
        session.commit()
    seen: list[list[str | None]] = []
    handed: list[Mapping[str, CameraCounters]] = []
    problem = ConnectionError("queue unreachable")

    def after_commit(
        stored: Sequence[tuple[Frame, bool]], counters: Mapping[str, CameraCounters]
    ) -> list[BaseException | None]:
        seen.append([f.client_frame_id for f, _ in stored])
        handed.append(counters)
        return [problem if f.client_frame_id == "k-2" else None for f, _ in stored]

    writer = FrameWriter(factory, after_commit=after_commit)
    with writer._wakeup:  # hold the thread back so that the three frames form one batch
        futures = [writer.submit(frame(cam, cid)) for cam, cid in ((kept, "k-1"), (gone, "g-1"), (kept, "k-2"))]
    answers = [future.exception(timeout=30) or future.result() for future in futures]
    writer.close()
    assert seen == [["k-1", "k-2"]]  # the refused frame is not passed on
    assert isinstance(answers[1], CameraNotFoundError)
    assert answers[0].after_commit_error is None and answers[2].after_commit_error is problem  # type: ignore[union-attr]
    assert answers[2].created  # type: ignore[union-attr]
    # The counters the batch's transaction left on the camera whose people it stored: the store's, after the commit.
    with factory() as session:
        stored_camera = session.get(Camera, "kept")
        assert stored_camera is not None
        assert handed == [{"kept": CameraCounters(stored_camera.epoch, stored_camera.usable_evidence_count, 0)}]
        assert stored_camera.usable_evidence_count == 4


def test_the_writer_survives_a_failing_after_commit_and_close_drains_the_queue(factory: sessionmaker[Session]) -> None:
    cam = camera(factory)
    calls = 0

    def after_commit(stored: Sequence[tuple[Frame, bool]], _counters: object) -> list[BaseException | None]:
        nonlocal calls
        calls += 1
        if calls == 1:
            raise RuntimeError("a bug in the hook")
        return [None] * len(stored)

    writer = FrameWriter(factory, after_commit=after_commit)
    with pytest.raises(RuntimeError, match="bug in the hook"):
        writer.add(frame(cam, "first"))  # stored, but its post is answered with the hook's error
    with writer._wakeup:
        queued = [writer.submit(frame(cam, f"later-{i}")) for i in range(5)]
        cancelled = writer.submit(frame(cam, "cancelled"))
        assert cancelled.cancel()  # its request went away before the writer took it
    writer.close()
    assert all(future.result(timeout=0).created for future in queued)
    with pytest.raises(RuntimeError, match="closed"):
        writer.submit(frame(cam, "too-late"))
    with factory() as session:
        stored = set(session.scalars(select(Frame.client_frame_id)))
    assert stored == {"first", *(f"later-{i}" for i in range(5))}
