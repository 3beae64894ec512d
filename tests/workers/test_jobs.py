"""The jobs' plumbing against a real Redis, a real migrated database and a real RQ worker (in this process): the
dispatcher, the per-camera gates and the recovery pass on start."""

from __future__ import annotations

import gc
import uuid
from pathlib import Path

import pytest
import redis
from rq import Queue
from sqlalchemy.orm import Session, sessionmaker

from service.dispatch import Dispatcher, DispatchUnavailableError
from service.geometry import evidence
from service.queue import CALIBRATION_QUEUE, FRAMES_QUEUE, CameraGate, RedisDispatcher, RequestOutcome, Ticket, connect
from service.settings import get_settings
from tests.support.jobs import frame_statuses, run_jobs, simulated_camera, store_frames, versions
from workers.main import requeue_pending, run_worker


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request: pytest.FixtureRequest) -> str:
    """The jobs' transactions, gates and bulk writes behave alike on both databases."""
    return str(request.param)


def test_redis_dispatcher_satisfies_the_protocol(redis_dispatcher: RedisDispatcher) -> None:
    assert isinstance(redis_dispatcher, Dispatcher)
    assert redis_dispatcher.ready()


def test_redis_down_raises_dispatch_unavailable(tmp_path: Path) -> None:
    down = RedisDispatcher(connect(f"unix://{tmp_path / 'no-redis.sock'}", timeout_s=0.5))
    assert not down.ready()
    with pytest.raises(DispatchUnavailableError):
        down.frames_stored([("cam", uuid.uuid4())])
    with pytest.raises(DispatchUnavailableError):
        down.calibration_requested("cam", False)


def test_a_full_redis_is_unavailable_not_an_error(connection: redis.Redis, redis_dispatcher: RedisDispatcher) -> None:
    """maxmemory reached with noeviction: Redis refuses writes (OOM; inside the gate's Lua script, wrapped in the
    script's error). The API must answer 503 queue-unavailable (the frame is stored), not 500, and the queues work
    again once Redis has room."""
    limit = connection.config_get("maxmemory")["maxmemory"]
    policy = connection.config_get("maxmemory-policy")["maxmemory-policy"]
    connection.config_set("maxmemory-policy", "noeviction")
    connection.config_set("maxmemory", "1")
    try:
        for ask in (
            lambda: redis_dispatcher.frames_stored([("cam", uuid.uuid4())]),  # the gate's script
            lambda: redis_dispatcher.calibration_requested("cam", False),  # the same script, called directly
            lambda: redis_dispatcher.image_stored("cam", uuid.uuid4()),  # plain commands (OutOfMemoryError)
        ):
            with pytest.raises(DispatchUnavailableError, match=r"OOM|maxmemory"):
                ask()
    finally:
        connection.config_set("maxmemory", limit)
        connection.config_set("maxmemory-policy", policy)
    assert redis_dispatcher.measure_requested(["cam"]) == 1


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
    connection: redis.Redis, redis_dispatcher: RedisDispatcher
) -> None:
    gate = redis_dispatcher.gates[FRAMES_QUEUE]
    assert gate.request("running", "j0") == RequestOutcome.ENQUEUED
    assert gate.start("running", "j0").run
    outcomes = gate.request_many([("idle", "j1"), ("running", "j2"), ("idle", "j3")])
    assert outcomes == [RequestOutcome.ENQUEUED, RequestOutcome.RERUN_SCHEDULED, RequestOutcome.ALREADY_QUEUED]
    # Through the redis_dispatcher: a camera named twice is asked once, and only granted slots become jobs.
    assert redis_dispatcher.measure_requested(["fresh", "idle", "fresh", "running"]) == 1
    assert [job.args[0] for job in Queue(FRAMES_QUEUE, connection=connection).get_jobs()] == ["fresh"]
    assert gate.state("fresh") == "queued" and gate.finish("running", "j0", "j4") is True


def test_a_batch_survives_redis_losing_its_scripts_between_the_check_and_the_send(
    connection: redis.Redis, redis_dispatcher: RedisDispatcher, monkeypatch: pytest.MonkeyPatch
) -> None:
    """serve's Redis killed and started again while a post's batch was on its way: the pipeline had found its
    script loaded on the old Redis, and the retry on the new one answered NOSCRIPT (a 500 in CI). The flush
    after the pipeline's check forces that interleaving on a real Redis."""
    gate = redis_dispatcher.gates[FRAMES_QUEUE]
    assert gate.request("running", "j0") == RequestOutcome.ENQUEUED and gate.start("running", "j0").run
    check_scripts = redis.client.Pipeline.load_scripts

    def restarted_after_the_check(pipe: redis.client.Pipeline) -> None:
        check_scripts(pipe)
        connection.script_flush()

    monkeypatch.setattr(redis.client.Pipeline, "load_scripts", restarted_after_the_check)
    outcomes = gate.request_many([("idle", "j1"), ("running", "j2")])
    assert outcomes == [RequestOutcome.ENQUEUED, RequestOutcome.RERUN_SCHEDULED]
    assert gate.state("idle") == "queued"


def test_two_requests_make_one_solve(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 8)
    assert redis_dispatcher.request(CALIBRATION_QUEUE, camera.camera_id) == RequestOutcome.ENQUEUED
    assert redis_dispatcher.request(CALIBRATION_QUEUE, camera.camera_id) == RequestOutcome.ALREADY_QUEUED
    redis_dispatcher.calibration_requested(camera.camera_id, False)
    assert Queue(CALIBRATION_QUEUE, connection=connection).count == 1
    run_jobs(connection)
    assert [v.version for v in versions(sessions, camera.camera_id)] == [1]
    assert redis_dispatcher.calibration_state(camera.camera_id) == "idle"


def test_requests_during_a_solve_make_exactly_one_rerun(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
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
            outcomes.extend(redis_dispatcher.request(CALIBRATION_QUEUE, camera.camera_id) for _ in range(3))
            assert redis_dispatcher.calibration_state(camera.camera_id) == "running"
        return solve(*args, **kwargs)

    monkeypatch.setattr(evidence, "calibrate", solve_while_requests_arrive)  # where the workers' solve calls it
    redis_dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    assert outcomes == [RequestOutcome.RERUN_SCHEDULED] * 3
    first, rerun = versions(sessions, camera.camera_id)
    assert (first.version, rerun.version) == (1, 2)
    assert rerun.evidence_count > first.evidence_count  # the re-run saw what arrived during the first solve
    assert redis_dispatcher.calibration_state(camera.camera_id) == "idle"


def test_requeue_on_start_is_idempotent(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    # Stored while Redis was "down": nothing was dispatched.
    store_frames(sessions, camera, 5)
    settings = get_settings()
    first = requeue_pending(settings, redis_dispatcher)
    second = requeue_pending(settings, redis_dispatcher)
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
    assert frame_statuses(sessions) == {"done": 5}
    assert [v.version for v in versions(sessions, camera.camera_id)] == [1]
