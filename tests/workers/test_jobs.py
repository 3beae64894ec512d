"""The jobs against a real Redis, a real migrated SQLite database and a real RQ worker (in this process)."""

from __future__ import annotations

import gc
import uuid
from pathlib import Path

import numpy as np
import pytest
import redis
from rq import Queue
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from service.dispatch import Dispatcher, DispatchUnavailableError
from service.geometry import evidence
from service.queue import (
    CALIBRATION_QUEUE,
    FRAMES_QUEUE,
    CameraGate,
    RedisDispatcher,
    RequestOutcome,
    Ticket,
    connect,
)
from service.settings import get_settings
from service.store import CalibrationVersion, Frame, Observation, ViolationEvent
from service.store.repository import CalibrationValues, calibration_history, current_calibration
from tests.workers.conftest import run_jobs, simulated_camera, store_frames
from workers import jobs
from workers.main import requeue_pending, run_worker


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request: pytest.FixtureRequest) -> str:
    """The jobs' transactions, gates and bulk writes behave alike on both databases."""
    return str(request.param)


def _versions(sessions: sessionmaker[Session], camera_id: str) -> list[CalibrationVersion]:
    with sessions() as session:
        return list(reversed(calibration_history(session, camera_id)))


def _frame_statuses(sessions: sessionmaker[Session]) -> dict[str, int]:
    with sessions() as session:
        rows = session.execute(select(Frame.status, func.count()).group_by(Frame.status)).all()
    return {status: int(count) for status, count in rows}


# --------------------------------------------------------------------------------------------------- dispatcher


def test_redis_dispatcher_satisfies_the_protocol(dispatcher: RedisDispatcher) -> None:
    assert isinstance(dispatcher, Dispatcher)
    assert dispatcher.ready()


def test_redis_down_raises_dispatch_unavailable(tmp_path: Path) -> None:
    down = RedisDispatcher(connect(f"unix://{tmp_path / 'no-redis.sock'}", timeout_s=0.5))
    assert not down.ready()
    with pytest.raises(DispatchUnavailableError):
        down.frames_stored([("cam", uuid.uuid4())])
    with pytest.raises(DispatchUnavailableError):
        down.calibration_requested("cam", False)


def test_frames_of_a_camera_make_one_measuring_job(
    sessions: sessionmaker[Session], dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions, people=40)
    other = simulated_camera(sessions, "cam-2", people=40)
    store_frames(sessions, camera, 3, dispatcher=dispatcher)
    store_frames(sessions, other, 1, dispatcher=dispatcher)
    jobs_queued = Queue(FRAMES_QUEUE, connection=connection).get_jobs()
    assert sorted(job.args[0] for job in jobs_queued) == ["cam-1", "cam-2"]
    assert dispatcher.state(FRAMES_QUEUE, "cam-1") == "queued"


def test_a_measuring_job_answers_every_pending_frame_in_chunks(
    sessions: sessionmaker[Session],
    dispatcher: RedisDispatcher,
    connection: redis.Redis,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    camera = simulated_camera(sessions, people=400)
    store_frames(sessions, camera, 8)
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    assert _frame_statuses(sessions) == {"done": 8}  # the first calibration asks for waiting frames
    store_frames(sessions, camera, 9)  # stored while Redis was "down": nobody asked for measuring
    monkeypatch.setattr(jobs, "FRAMES_CHUNK", 4)
    assert jobs.measure_frames(camera.camera_id) == jobs.DONE
    assert _frame_statuses(sessions) == {"done": 17}  # three chunks: 4 + 4 + 1


def test_a_measuring_job_over_its_budget_queues_its_own_rerun(
    sessions: sessionmaker[Session],
    dispatcher: RedisDispatcher,
    connection: redis.Redis,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    camera = simulated_camera(sessions, people=400)
    store_frames(sessions, camera, 8)
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    store_frames(sessions, camera, 8)
    monkeypatch.setattr(jobs, "FRAMES_CHUNK", 3)
    monkeypatch.setattr(jobs, "FRAMES_JOB_BUDGET_S", -1.0)  # out of budget after the first chunk
    assert jobs.measure_frames(camera.camera_id) == jobs.DONE
    assert _frame_statuses(sessions) == {"done": 11, "pending": 5}
    assert [job.args[0] for job in Queue(FRAMES_QUEUE, connection=connection).get_jobs()] == [camera.camera_id]
    run_jobs(connection)
    assert _frame_statuses(sessions) == {"done": 16}


# --------------------------------------------------------------------------------------------------- calibration gate


def test_keying_takes_every_unkeyed_person_in_transactions_sized_to_the_time_bound(
    sessions: sessionmaker[Session], monkeypatch: pytest.MonkeyPatch
) -> None:
    camera = simulated_camera(sessions, people=300)
    other = simulated_camera(sessions, "cam-2", people=40)
    store_frames(sessions, camera, 30)
    store_frames(sessions, other, 2)
    limits: list[int] = []
    real = jobs.key_new_evidence

    def recording(session: Session, camera_id: str, *, limit: int) -> int:
        limits.append(limit)
        return real(session, camera_id, limit=limit)

    monkeypatch.setattr(jobs, "key_new_evidence", recording)
    monkeypatch.setattr(jobs, "KEY_CHUNK", 50)
    monkeypatch.setattr(jobs, "KEY_CHUNK_BOUNDS", (7, 7))  # whatever the clock says, then 7 per transaction
    people = select(Observation.camera_id, func.count()).group_by(Observation.camera_id)
    with sessions() as session:
        stored = dict(session.execute(people).all())
    assert stored["cam-1"] > 50
    assert jobs.key_camera_evidence(get_settings(), "cam-1") == stored["cam-1"]
    assert limits[0] == 50 and set(limits[1:]) == {7} and len(limits) == 1 + -(-(stored["cam-1"] - 50 + 1) // 7)
    with sessions() as session:
        unkeyed = dict(session.execute(people.where(Observation.sample_key.is_(None))).all())
    assert unkeyed == {"cam-2": stored["cam-2"]}  # other cameras wait for their own solve


def test_gate_states_and_forced_flag(connection: redis.Redis) -> None:
    gate = CameraGate(connection, CALIBRATION_QUEUE, queued_ttl_s=60)
    assert gate.request("c", "j1", forced=False) == RequestOutcome.ENQUEUED
    assert gate.request("c", "j2", forced=True) == RequestOutcome.ALREADY_QUEUED
    assert gate.state("c") == "queued"
    ticket = gate.start("c", "j1")
    assert ticket.run and ticket.forced  # the forced request was folded into the queued solve
    assert gate.state("c") == "running"
    assert gate.start("c", "j-other").run is False  # never two solves of one camera
    assert gate.request("c", "j3", forced=False) == RequestOutcome.RERUN_SCHEDULED
    assert gate.request("c", "j4", forced=False) == RequestOutcome.RERUN_SCHEDULED
    assert gate.finish("c", "j1", "j5") is True  # one re-run, however many requests came in
    assert gate.state("c") == "queued"
    assert gate.start("c", "j5") == Ticket(run=True, forced=False)
    assert gate.refresh("c", "j5") and not gate.refresh("c", "j-other")
    assert gate.finish("c", "j5", "j6") is False
    assert gate.state("c") == "idle"


def test_a_batch_of_requests_is_one_round_trip_with_an_outcome_each(
    connection: redis.Redis, dispatcher: RedisDispatcher
) -> None:
    gate = dispatcher.gates[FRAMES_QUEUE]
    assert gate.request("running", "j0") == RequestOutcome.ENQUEUED
    assert gate.start("running", "j0").run
    outcomes = gate.request_many([("idle", "j1"), ("running", "j2"), ("idle", "j3")])
    assert outcomes == [RequestOutcome.ENQUEUED, RequestOutcome.RERUN_SCHEDULED, RequestOutcome.ALREADY_QUEUED]
    # Through the dispatcher: a camera named twice is asked once, and only granted slots become jobs.
    assert dispatcher.measure_requested(["fresh", "idle", "fresh", "running"]) == 1
    assert [job.args[0] for job in Queue(FRAMES_QUEUE, connection=connection).get_jobs()] == ["fresh"]
    assert gate.state("fresh") == "queued" and gate.finish("running", "j0", "j4") is True


def test_two_requests_make_one_solve(
    sessions: sessionmaker[Session], dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 8)
    assert dispatcher.request(CALIBRATION_QUEUE, camera.camera_id) == RequestOutcome.ENQUEUED
    assert dispatcher.request(CALIBRATION_QUEUE, camera.camera_id) == RequestOutcome.ALREADY_QUEUED
    dispatcher.calibration_requested(camera.camera_id, False)
    assert Queue(CALIBRATION_QUEUE, connection=connection).count == 1
    run_jobs(connection)
    assert [v.version for v in _versions(sessions, camera.camera_id)] == [1]
    assert dispatcher.calibration_state(camera.camera_id) == "idle"


def test_requests_during_a_solve_make_exactly_one_rerun(
    sessions: sessionmaker[Session],
    dispatcher: RedisDispatcher,
    connection: redis.Redis,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 8)
    solve = evidence.calibrate
    outcomes: list[int] = []

    def solve_while_requests_arrive(*args, **kwargs):  # type: ignore[no-untyped-def]
        if not outcomes:  # the first solve, after it sampled: more evidence arrives, each frame nudging calibration
            store_frames(sessions, camera, 5)
            outcomes.extend(dispatcher.request(CALIBRATION_QUEUE, camera.camera_id) for _ in range(3))
            assert dispatcher.calibration_state(camera.camera_id) == "running"
        return solve(*args, **kwargs)

    monkeypatch.setattr(evidence, "calibrate", solve_while_requests_arrive)  # where the workers' solve calls it
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    assert outcomes == [RequestOutcome.RERUN_SCHEDULED] * 3
    first, rerun = _versions(sessions, camera.camera_id)
    assert (first.version, rerun.version) == (1, 2)
    assert rerun.evidence_count > first.evidence_count  # the re-run saw what arrived during the first solve
    assert dispatcher.calibration_state(camera.camera_id) == "idle"


def test_unforced_requests_without_new_evidence_do_not_solve(
    sessions: sessionmaker[Session], dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 8)
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)  # e.g. frames that saw "due" while the first solve ran
    run_jobs(connection)
    assert [v.version for v in _versions(sessions, camera.camera_id)] == [1]
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id, forced=True)
    run_jobs(connection)
    assert [(v.version, v.forced) for v in _versions(sessions, camera.camera_id)] == [(1, False), (2, True)]


# --------------------------------------------------------------------------------------------------- end to end


def test_pending_frames_are_answered_after_the_first_calibration(
    sessions: sessionmaker[Session], dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    # 2 frames: 20 people, not enough for a first solve (30); they wait, pending.
    early = store_frames(sessions, camera, 2, dispatcher=dispatcher)
    run_jobs(connection)
    assert _frame_statuses(sessions) == {"pending": 2}
    assert _versions(sessions, camera.camera_id) == []
    # More frames: the frame jobs find calibration due and nudge it; the solve then re-enqueues every pending one.
    store_frames(sessions, camera, 3, dispatcher=dispatcher)
    run_jobs(connection)
    assert _frame_statuses(sessions) == {"done": 5}
    (version,) = _versions(sessions, camera.camera_id)
    assert version.is_current and version.status == "ok" and version.evidence_count >= 30
    assert version.fx_px == pytest.approx(camera.scene.fx, rel=0.1)
    truth = np.asarray(camera.scene.normal)
    normal = np.array([version.normal_x, version.normal_y, version.normal_z])
    assert np.degrees(np.arccos(min(1.0, float(normal @ truth)))) < 5.0

    with sessions() as session:
        frame = session.get(Frame, early[0])
        assert frame is not None and frame.result is not None
        assert frame.calibration_version == 1
        pairs = frame.result["pairs"]
        assert len(pairs) == 10 * 9 // 2
        # Distances against the simulator's truth (points in the camera frame).
        x = camera.scene.points_bottom[:10]
        for pair in pairs:
            true_m = float(np.linalg.norm(x[pair["i"]] - x[pair["j"]]))
            assert pair["distance_m"] == pytest.approx(true_m, rel=0.15, abs=0.3)
        events = session.scalar(select(func.count()).select_from(ViolationEvent))
        violations = sum(len(session.get(Frame, f).result["violations"]) for f in early)  # type: ignore[union-attr]
        assert events is not None and events >= violations


def test_version_becomes_current_only_when_as_well_supported_unless_forced(
    sessions: sessionmaker[Session],
    dispatcher: RedisDispatcher,
    connection: redis.Redis,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 20)
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    # Evidence doubles, but the solve runs on a tiny sample: fewer inliers and less precise, so it must not
    # replace version 1...
    store_frames(sessions, camera, 20)
    monkeypatch.setenv("POSEMETRY_CALIBRATION_SAMPLE_CAP", "12")
    get_settings.cache_clear()
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    # ...unless forced.
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id, forced=True)
    run_jobs(connection)
    first, weak, forced = _versions(sessions, camera.camera_id)
    assert (first.status, weak.status, forced.status) == ("ok", "ok", "ok")
    assert weak.inliers < first.inliers and not weak.is_current and not weak.forced
    assert forced.is_current and forced.forced
    with sessions() as session:
        current = current_calibration(session, camera.camera_id)
        assert current is not None and current.version == 3


def test_at_least_as_supported_rule() -> None:
    current = CalibrationVersion(status="ok", inliers=100, fx_px=1000.0, fx_std_px=20.0, normal_std_deg=1.0)

    def new(inliers: int, fx_std_px: float | None, normal_std_deg: float | None) -> CalibrationValues:
        return CalibrationValues(
            status="ok",
            person_height_m=1.7,
            people_used=inliers,
            inliers=inliers,
            evidence_count=inliers,
            fx_px=1000.0,
            fx_std_px=fx_std_px,
            normal_std_deg=normal_std_deg,
        )

    assert jobs.at_least_as_supported(new(100, 40.0, 3.0), current)  # as many inliers
    assert jobs.at_least_as_supported(new(90, 15.0, 0.8), current)  # fewer, but more precise on both
    assert not jobs.at_least_as_supported(new(90, 15.0, 1.5), current)  # fewer and the normal less certain
    assert not jobs.at_least_as_supported(new(90, None, None), current)  # no uncertainty: not better
    failed = CalibrationValues.failure("x", person_height_m=1.7, people_used=0, evidence_count=0)
    assert not jobs.at_least_as_supported(failed, current)


def test_calibration_error_is_recorded_and_the_worker_carries_on(
    sessions: sessionmaker[Session], dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions, people=60)
    store_frames(sessions, camera, 1, people=1, dispatcher=dispatcher)
    dispatcher.request(CALIBRATION_QUEUE, camera.camera_id, forced=True)
    run_jobs(connection)
    (version,) = _versions(sessions, camera.camera_id)
    assert version.status == "failed" and version.reason and not version.is_current
    assert _frame_statuses(sessions) == {"pending": 1}
    assert Queue(CALIBRATION_QUEUE, connection=connection).failed_job_registry.count == 0
    assert dispatcher.calibration_state(camera.camera_id) == "idle"
    # Nothing is stuck: once evidence suffices the camera calibrates and the waiting frame is answered too.
    store_frames(sessions, camera, 4, dispatcher=dispatcher)
    run_jobs(connection)
    assert [(v.version, v.status, v.is_current) for v in _versions(sessions, camera.camera_id)] == [
        (1, "failed", False),
        (2, "ok", True),
    ]
    assert _frame_statuses(sessions) == {"done": 5}


def test_requeue_on_start_is_idempotent(
    sessions: sessionmaker[Session], dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    # Stored while Redis was "down": nothing was dispatched.
    store_frames(sessions, camera, 5)
    settings = get_settings()
    first = requeue_pending(settings, dispatcher)
    second = requeue_pending(settings, dispatcher)
    # The camera is not calibrated yet: its frames are measured when the solve it is due becomes current.
    assert (first.frames, first.calibrations) == (0, 1)
    assert second.calibrations == 1 and Queue(CALIBRATION_QUEUE, connection=connection).count == 1  # deduplicated
    assert Queue(FRAMES_QUEUE, connection=connection).count == 0
    # A worker start (burst: drain and exit) re-enqueues nothing twice and answers everything.
    gc.unfreeze()
    try:
        requeued = run_worker(burst=True)
        assert gc.get_freeze_count() > 10_000  # start-up objects out of the collector's sight before the first job
    finally:
        gc.unfreeze()
    assert requeued.frames == 0
    assert _frame_statuses(sessions) == {"done": 5}
    assert [v.version for v in _versions(sessions, camera.camera_id)] == [1]
