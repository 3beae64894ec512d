"""The measuring job against a real Redis, a real migrated database and a real RQ worker (in this process)."""

from __future__ import annotations

import pytest
import redis
from rq import Queue
from sqlalchemy.orm import Session, sessionmaker

from service.domain import DONE
from service.frames import service as frames_service
from service.queue import CALIBRATION_QUEUE, FRAMES_QUEUE, RedisDispatcher
from tests.support.jobs import frame_statuses, run_jobs, simulated_camera, store_frames
from workers import jobs


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request: pytest.FixtureRequest) -> str:
    """The jobs' transactions, gates and bulk writes behave alike on both databases."""
    return str(request.param)


def test_frames_of_a_camera_make_one_measuring_job(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions, people=40)
    other = simulated_camera(sessions, "cam-2", people=40)
    store_frames(sessions, camera, 3, dispatcher=redis_dispatcher)
    store_frames(sessions, other, 1, dispatcher=redis_dispatcher)
    jobs_queued = Queue(FRAMES_QUEUE, connection=connection).get_jobs()
    assert sorted(job.args[0] for job in jobs_queued) == ["cam-1", "cam-2"]
    assert redis_dispatcher.state(FRAMES_QUEUE, "cam-1") == "queued"


def test_a_measuring_job_answers_every_pending_frame_in_chunks(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    camera = simulated_camera(sessions, people=400)
    store_frames(sessions, camera, 8)
    redis_dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    assert frame_statuses(sessions) == {"done": 8}  # the first calibration asks for waiting frames
    store_frames(sessions, camera, 9)  # stored while Redis was "down": nobody asked for measuring
    monkeypatch.setattr(frames_service, "FRAMES_CHUNK", 4)
    assert jobs.measure_frames(camera.camera_id) == DONE
    assert frame_statuses(sessions) == {"done": 17}  # three chunks: 4 + 4 + 1


def test_a_measuring_job_over_its_budget_queues_its_own_rerun(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    camera = simulated_camera(sessions, people=400)
    store_frames(sessions, camera, 8)
    redis_dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    store_frames(sessions, camera, 8)
    monkeypatch.setattr(frames_service, "FRAMES_CHUNK", 3)
    monkeypatch.setattr(frames_service, "FRAMES_JOB_BUDGET_S", -1.0)  # out of budget after the first chunk
    assert jobs.measure_frames(camera.camera_id) == DONE
    assert frame_statuses(sessions) == {"done": 11, "pending": 5}
    assert [job.args[0] for job in Queue(FRAMES_QUEUE, connection=connection).get_jobs()] == [camera.camera_id]
    run_jobs(connection)
    assert frame_statuses(sessions) == {"done": 16}
