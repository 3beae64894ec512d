"""What lets the workers recover from a dead job or a lost nudge, on a real Redis: the camera gate's running slot
(lapses without heartbeat, lets the same job back in, keeps a forced request until a run completes), the
per-process pacemaker, and the recovery pass's schedule. The process tests in tests/faults kill real workers."""

from __future__ import annotations

import threading

import pytest
import redis
from rq import Queue, SimpleWorker
from rq.executions import ExecutionRegistry
from rq.job import Job
from sqlalchemy.orm import Session, sessionmaker

from service.queue import (
    CALIBRATION_QUEUE,
    FRAMES_QUEUE,
    JOB_LIVENESS_TTL_S,
    CameraGate,
    RedisDispatcher,
    RequestOutcome,
)
from service.settings import get_settings
from tests.support.jobs import simulated_camera, store_frames
from workers import recovery
from workers.liveness import Pacemaker, forget_dead_executions
from workers.main import requeue_pending


def test_a_running_slot_lives_only_while_its_job_beats(connection: redis.Redis) -> None:
    gate = CameraGate(connection, CALIBRATION_QUEUE, queued_ttl_s=600)
    lock = gate.keys("c")[0]
    assert gate.request("c", "j1") == RequestOutcome.ENQUEUED
    assert connection.ttl(lock) > JOB_LIVENESS_TTL_S  # waiting in the queue may take long
    assert gate.start("c", "j1").run
    assert 0 < connection.ttl(lock) <= JOB_LIVENESS_TTL_S  # running: only as long as the heartbeat says
    connection.expire(lock, 1)
    assert gate.refresh("c", "j1") and connection.ttl(lock) > 1  # the heartbeat pushes it out again
    assert gate.request("c", "j2") == RequestOutcome.RERUN_SCHEDULED
    # The job's process dies: no more beats, the slot lapses (deleted here rather than waited for).
    connection.delete(lock)
    assert not gate.refresh("c", "j1")
    # RQ retries the dead job under its own id: it takes the slot again, and the re-run it owed is moot (it
    # reads everything that arrived before it started).
    assert gate.start("c", "j1").run
    assert gate.finish("c", "j1", "j3") is False
    assert gate.state("c") == "idle"


def test_a_request_after_a_lapsed_slot_queues_one_job_and_drops_the_stale_rerun(connection: redis.Redis) -> None:
    gate = CameraGate(connection, CALIBRATION_QUEUE, queued_ttl_s=600)
    gate.request("c", "j1")
    gate.start("c", "j1")
    gate.request("c", "j2")  # a re-run flag for a job that then dies
    connection.delete(gate.keys("c")[0])
    assert gate.request("c", "j3") == RequestOutcome.ENQUEUED
    assert gate.start("c", "j3").run
    assert gate.finish("c", "j3", "j4") is False  # no second job for the dead one's flag


def test_a_forced_request_stands_until_a_run_of_it_completes(connection: redis.Redis) -> None:
    gate = CameraGate(connection, CALIBRATION_QUEUE, queued_ttl_s=600)
    gate.request("c", "j1", forced=True)
    assert gate.start("c", "j1").forced
    assert gate.forced_outstanding(["c", "other"]) == ["c"]
    gate.finish("c", "j1", "j2", completed=False)  # the solve raised (say, the database went away)
    assert gate.forced_outstanding(["c"]) == ["c"]
    assert gate.start("c", "j1").forced  # its retry is still forced
    gate.finish("c", "j1", "j2", completed=True)
    assert gate.forced_outstanding(["c"]) == []
    gate.request("c", "j3")
    assert not gate.start("c", "j3").forced


def test_the_recovery_pass_asks_again_for_a_forced_solve_that_failed(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 1)  # 10 people: not due (30 needed)
    gate = redis_dispatcher.gates[CALIBRATION_QUEUE]
    gate.request(camera.camera_id, "j1", forced=True)
    gate.start(camera.camera_id, "j1")
    gate.finish(camera.camera_id, "j1", "j2", completed=False)
    assert requeue_pending(get_settings(), redis_dispatcher).calibrations == 1
    assert Queue(CALIBRATION_QUEUE, connection=connection).count == 1


def test_a_queued_slot_whose_job_waits_nowhere_is_freed(
    redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    gate, queue = redis_dispatcher.gates[FRAMES_QUEUE], Queue(FRAMES_QUEUE, connection=connection)
    for camera_id in ("waiting", "taken", "started"):
        assert redis_dispatcher.measure_requested([camera_id]) == 1
    job_ids = dict(gate.queued_claims(["waiting", "taken", "started"]))
    gate.request("never-queued", "frames-lost")  # the API died between the gate and the enqueue
    # A worker took the job off the queue and died before RQ marked it started: RQ's cleanup skips such a job.
    connection.lrem(queue.key, 0, job_ids["taken"])
    # A started job is RQ's to see through (retried if its process dies).
    connection.lrem(queue.key, 0, job_ids["started"])
    connection.hset(Job.key_for(job_ids["started"]), "status", "started")
    cameras = ["waiting", "taken", "started", "never-queued", "idle"]
    assert redis_dispatcher.release_lost_claims(FRAMES_QUEUE, cameras) == 2
    assert [gate.state(c) for c in cameras] == ["queued", "idle", "queued", "idle", "idle"]
    assert redis_dispatcher.release_lost_claims(FRAMES_QUEUE, cameras) == 0


def test_the_recovery_pass_queues_again_a_camera_whose_queued_job_was_lost(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 1)  # 10 people: not due (30 needed)
    gate = redis_dispatcher.gates[CALIBRATION_QUEUE]
    gate.request(camera.camera_id, "calibration-lost", forced=True)  # never reached the queue
    assert requeue_pending(get_settings(), redis_dispatcher).calibrations == 1
    assert [job.args[0] for job in Queue(CALIBRATION_QUEUE, connection=connection).get_jobs()] == [camera.camera_id]


def test_the_pacemaker_beats_every_registered_job_until_it_ends() -> None:
    pacemaker = Pacemaker(0.01)
    beats = {"a": threading.Semaphore(0), "b": threading.Semaphore(0)}

    def failing() -> None:
        beats["b"].release()
        raise redis.ConnectionError("Redis unreachable for a moment")

    with pacemaker.beating(beats["a"].release), pacemaker.beating(failing):
        for _ in range(3):  # a failing beat neither stops the thread nor the other beats
            assert beats["a"].acquire(timeout=10) and beats["b"].acquire(timeout=10)
    while beats["a"].acquire(timeout=0.05):  # drain a beat that raced the end of the block
        pass
    assert not beats["a"].acquire(timeout=0.1)


@pytest.fixture
def schedules(connection: redis.Redis) -> tuple[list[str], recovery.RecoverySchedule, recovery.RecoverySchedule]:
    runs: list[str] = []
    return (
        runs,
        recovery.RecoverySchedule(connection, lambda: runs.append("first")),
        recovery.RecoverySchedule(connection, lambda: runs.append("second")),
    )


def test_one_worker_runs_the_periodic_pass_and_any_runs_it_when_asked(
    connection: redis.Redis, schedules: tuple[list[str], recovery.RecoverySchedule, recovery.RecoverySchedule]
) -> None:
    runs, first, second = schedules
    assert first.run_if_due() and not second.run_if_due()  # once per RECOVERY_INTERVAL_S, on one worker
    assert connection.ttl(recovery.SCHEDULE_KEY) > 0
    recovery.request_recovery(connection)  # a job met an unavailable database
    assert second.run_if_due() and not first.run_if_due()
    assert runs == ["first", "second"]
    connection.delete(recovery.SCHEDULE_KEY)  # what a Redis restarted empty looks like: due at once
    assert second.run_if_due()


def test_a_failed_pass_is_tried_again_at_the_next_maintenance(connection: redis.Redis) -> None:
    attempts: list[int] = []

    def recover() -> None:
        attempts.append(1)
        if len(attempts) == 1:
            raise ConnectionError("database still down")

    schedule = recovery.RecoverySchedule(connection, recover)
    assert not schedule.run_if_due()
    assert connection.exists(recovery.DUE_KEY) and not connection.exists(recovery.LOCK_KEY)
    assert schedule.run_if_due() and len(attempts) == 2
    assert not connection.exists(recovery.DUE_KEY)


def test_a_dead_execution_does_not_fail_the_retried_jobs_success(connection: redis.Redis) -> None:
    """RQ 3.0 keeps a dead execution in its job's registry a minute longer than the execution itself; deleting the
    job then (a retried job that succeeded, result_ttl=0) fails unless the dead execution is forgotten first."""
    queue = Queue("frames", connection=connection)
    worker = SimpleWorker([queue], connection=connection)

    def dead_job() -> Job:
        job = queue.enqueue("time.sleep", 0, result_ttl=0)
        execution = worker.prepare_execution(job)  # its process then dies: the execution's hash expires first
        connection.delete(execution.key)
        connection.zadd(job.started_job_registry.key, {execution.composite_key: 1})  # its heartbeat lapsed
        return job

    unrepaired = dead_job()
    with pytest.raises(ValueError, match="not found in Redis"):
        unrepaired.delete()
    job = dead_job()
    forget_dead_executions(connection, [queue])
    assert ExecutionRegistry(job.id, connection=connection).get_execution_ids() == []
    job.delete()
