"""Job metrics, queue depths and request ids through real jobs on a real Redis (in this process)."""

from __future__ import annotations

import io
import uuid
from datetime import timedelta
from pathlib import Path

import pytest
import redis
from fastapi import FastAPI
from fastapi.testclient import TestClient
from prometheus_client import REGISTRY
from rq import Queue, get_current_job
from sqlalchemy.orm import Session, sessionmaker

from service.app import create_app
from service.observability.queue_depths import QueueDepths
from service.observability.request_id import JOB_META_KEY
from service.queue import CALIBRATION_QUEUE, FRAMES_QUEUE, POSE_QUEUE, QUEUES, RedisDispatcher, connect
from service.settings import get_settings
from service.store import Frame
from service.store import sessions as store_sessions
from tests.support.app import ADMIN_KEY, bearer
from tests.support.jobs import IMAGE_SIZE, frame_timestamp, simulated_camera, store_frames
from tests.support.logs import json_lines, json_log
from tests.support.scrape import Scrape
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir
from workers.instrumented import InstrumentedSimpleWorker, InstrumentedWorker
from workers.main import run_worker

__all__ = ["json_log"]  # a fixture

FAILING_JOB = "workers.jobs.detect_people"  # with an argument that is no frame id, it raises ValueError


def queue_depths_seen_by_a_running_job() -> dict[tuple[str, str], int]:
    """A job that reads the queue depths while it runs (so its own queue has one started job)."""
    job = get_current_job()
    assert job is not None
    return QueueDepths(job.connection, QUEUES).read()


def sample(name: str, **labels: str) -> float:
    return REGISTRY.get_sample_value(name, labels) or 0.0


def job_count(queue: str, outcome: str) -> float:
    return sample("posemetry_job_duration_seconds_count", queue=queue, outcome=outcome)


def drain(connection: redis.Redis, queues: tuple[str, ...] = QUEUES, *, fork: bool = False) -> None:
    worker_class = InstrumentedWorker if fork else InstrumentedSimpleWorker
    worker_class([Queue(name, connection=connection) for name in queues], connection=connection).work(burst=True)


@pytest.fixture
def app(redis_dispatcher: RedisDispatcher, connection: redis.Redis) -> FastAPI:
    return create_app(get_settings(), dispatcher=redis_dispatcher, queue_depths=QueueDepths(connection, QUEUES))


def scrape(app: FastAPI) -> Scrape:
    with TestClient(app, headers=bearer(ADMIN_KEY)) as client:
        response = client.get("/metrics")
    assert response.status_code == 200
    return Scrape(response.text)


# --------------------------------------------------------------------------------------------------- queues


def test_queue_depths_are_read_from_redis_at_scrape_time(
    app: FastAPI, sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    for camera_id in ("cam-1", "cam-2"):
        redis_dispatcher.request(FRAMES_QUEUE, camera_id)
    Queue(POSE_QUEUE, connection=connection).enqueue(FAILING_JOB, "not-a-frame-id", failure_ttl=600)
    drain(connection, (POSE_QUEUE,))
    # Any queue name is reported, e.g. a webhook queue with a delivery waiting for its retry.
    Queue("webhooks", connection=connection).enqueue_in(timedelta(hours=1), FAILING_JOB, "later")
    running = Queue(CALIBRATION_QUEUE, connection=connection).enqueue(queue_depths_seen_by_a_running_job, result_ttl=60)
    drain(connection, (CALIBRATION_QUEUE,))
    assert running.return_value()[(CALIBRATION_QUEUE, "started")] == 1

    metrics = scrape(app)
    depth = {(labels["queue"], labels["state"]): v for labels, v in _values(metrics, "posemetry_queue_jobs")}
    assert depth[(FRAMES_QUEUE, "queued")] == 2
    assert depth[(POSE_QUEUE, "failed")] == 1 and depth[(POSE_QUEUE, "queued")] == 0
    assert depth[("webhooks", "scheduled")] == 1
    assert depth[(CALIBRATION_QUEUE, "started")] == 0  # the job has finished
    assert {queue for queue, _state in depth} == {*QUEUES, "webhooks"}
    assert all(value == 0 for (queue, state), value in depth.items() if queue == CALIBRATION_QUEUE)
    assert metrics.value("posemetry_metrics_source_up", source="redis") == 1


def test_an_unreachable_redis_leaves_the_scrape_answering(tmp_path: Path, environment: dict[str, str]) -> None:
    down = connect(f"unix://{tmp_path / 'no-redis.sock'}", timeout_s=0.5)
    app = create_app(get_settings(), queue_depths=QueueDepths(down, QUEUES))
    metrics = scrape(app)
    assert metrics.value("posemetry_metrics_source_up", source="redis") == 0
    assert metrics.value("posemetry_metrics_source_up", source="database") == 1
    assert metrics.labelsets("posemetry_queue_jobs") == []


def _values(metrics: Scrape, name: str) -> list[tuple[dict[str, str], float]]:
    return [(s.labels, s.value) for s in metrics.samples if s.name == name]


# --------------------------------------------------------------------------------------------------- jobs


def test_job_durations_and_failures_per_queue_after_real_jobs(
    app: FastAPI, sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    before = {
        "frames": job_count(FRAMES_QUEUE, "succeeded"),
        "calibration": job_count(CALIBRATION_QUEUE, "succeeded"),
        "pose failed": job_count(POSE_QUEUE, "failed"),
        "pose failures": sample("posemetry_job_failures_total", queue=POSE_QUEUE),
        "frames failures": sample("posemetry_job_failures_total", queue=FRAMES_QUEUE),
        "calibration seconds": sample(
            "posemetry_job_duration_seconds_sum", queue=CALIBRATION_QUEUE, outcome="succeeded"
        ),
    }
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 4, dispatcher=redis_dispatcher)  # 40 people: the measuring job asks for a solve
    Queue(POSE_QUEUE, connection=connection).enqueue(FAILING_JOB, "not-a-frame-id")
    drain(connection)
    metrics = scrape(app)  # what Prometheus sees, not only the registry
    assert metrics.value("posemetry_job_duration_seconds_count", queue=FRAMES_QUEUE, outcome="succeeded") >= (
        before["frames"] + 2  # before the solve (frames stay pending) and after it (frames measured)
    )
    assert metrics.value("posemetry_job_duration_seconds_count", queue=CALIBRATION_QUEUE, outcome="succeeded") == (
        before["calibration"] + 1
    )
    solve_s = sample("posemetry_job_duration_seconds_sum", queue=CALIBRATION_QUEUE, outcome="succeeded")
    assert 0.01 < solve_s - before["calibration seconds"] < 60
    assert metrics.value("posemetry_job_duration_seconds_count", queue=POSE_QUEUE, outcome="failed") == (
        before["pose failed"] + 1
    )
    assert metrics.value("posemetry_job_failures_total", queue=POSE_QUEUE) == before["pose failures"] + 1
    assert metrics.value("posemetry_job_failures_total", queue=FRAMES_QUEUE) == before["frames failures"]
    assert all(sample("posemetry_jobs_in_progress", queue=queue) == 0 for queue in QUEUES)


def test_a_forking_worker_measures_its_jobs_from_the_parent(
    sessions: sessionmaker[Session], connection: redis.Redis
) -> None:
    before = (job_count(POSE_QUEUE, "succeeded"), job_count(POSE_QUEUE, "failed"))
    queue = Queue(POSE_QUEUE, connection=connection)
    queue.enqueue(FAILING_JOB, str(uuid.uuid4()), result_ttl=0)  # no such frame: returns `gone`, job deleted
    queue.enqueue(FAILING_JOB, "not-a-frame-id")

    store_sessions.dispose_engines()  # as run_worker does: the job process must not share the parent's connections
    drain(connection, (POSE_QUEUE,), fork=True)
    assert (job_count(POSE_QUEUE, "succeeded"), job_count(POSE_QUEUE, "failed")) == (before[0] + 1, before[1] + 1)


# --------------------------------------------------------------------------------------------------- request ids


def test_request_ids_follow_frames_into_the_measuring_job(
    app: FastAPI, sessions: sessionmaker[Session], connection: redis.Redis, json_log: io.StringIO
) -> None:
    scene = simulated_camera(sessions, "lobby")  # its people; the camera itself is created over HTTP below
    posted: dict[str, str] = {}
    with TestClient(app, headers=bearer(ADMIN_KEY)) as client:
        settings = {"image_width_px": IMAGE_SIZE[0], "image_height_px": IMAGE_SIZE[1], "person_height_m": 1.7}
        assert client.put("/v1/cameras/lobby", json=settings).status_code == 200
        for index in range(4):  # 40 people: enough to calibrate (POSEMETRY_CALIBRATION_MIN_PEOPLE=30)
            tops, bottoms = scene.frame_people()
            people = [{"shoulder": t.tolist(), "ankle": b.tolist()} for t, b in zip(tops, bottoms, strict=True)]
            body = {"timestamp": frame_timestamp(index), "people": people}
            response = client.post(
                "/v1/cameras/lobby/keypoints", json=body, headers={"X-Request-ID": f"cam-req-{index}"}
            )
            assert response.status_code == 202
            posted[response.json()["frame_id"]] = f"cam-req-{index}"
    with sessions() as session:
        assert {str(f.id): f.request_id for f in session.query(Frame)} == posted
    run_worker((FRAMES_QUEUE, CALIBRATION_QUEUE), burst=True)

    lines = json_lines(json_log)
    measured = [line for line in lines if line["logger"] == "workers.jobs" and "measured" in line["message"]]
    # The frames are measured in one batch by one job, yet each line carries the id of the request that posted it.
    assert {line["frame_id"]: line["request_id"] for line in measured} == posted
    assert len({line["job_id"] for line in measured}) == 1
    assert all(line["queue"] == FRAMES_QUEUE and line["camera_id"] == "lobby" for line in measured)
    assert all(line["frame_status"] == "done" and line["calibration_version"] == 1 for line in measured)
    access = [line for line in lines if line["logger"] == "posemetry.access" and line["method"] == "POST"]
    assert [line["request_id"] for line in access] == list(posted.values())


def test_an_image_frames_pose_job_logs_under_its_request_id(
    app: FastAPI, connection: redis.Redis, json_log: io.StringIO
) -> None:
    jpeg = (require_dir(TOWN_CENTRE, "Town Centre data") / "frames" / "clip_000000.jpg").read_bytes()
    require_dir(model_dir_path(), "pose model")
    inference_before = _pose_inferences()
    with TestClient(app, headers=bearer(ADMIN_KEY)) as client:
        client.put("/v1/cameras/street", json={"image_width_px": 1920, "image_height_px": 1080})
        response = client.post(
            "/v1/cameras/street/frames",
            content=jpeg,
            headers={"content-type": "image/jpeg", "X-Request-ID": "image-req-7"},
        )
    assert response.status_code == 202, response.text
    frame_id = response.json()["frame_id"]
    (job,) = Queue(POSE_QUEUE, connection=connection).get_jobs()
    assert job.meta[JOB_META_KEY] == "image-req-7"
    drain(connection, (POSE_QUEUE,))

    lines = json_lines(json_log)
    found = next(line for line in lines if line["logger"] == "workers.jobs" and "people found" in line["message"])
    assert found["request_id"] == "image-req-7" and found["frame_id"] == frame_id and found["camera_id"] == "street"
    assert found["queue"] == POSE_QUEUE and found["job_id"] == job.id and found["people"] >= 8
    # RQ's own lines written while it runs the job carry the request id too (from the job's meta).
    job_ok = next(line for line in lines if line["logger"] == "rq.worker" and f"Job OK ({job.id})" in line["message"])
    assert job_ok["request_id"] == "image-req-7" and job_ok["job_id"] == job.id
    assert _pose_inferences() == inference_before + 1


def _pose_inferences() -> float:
    return sum(
        s.value
        for family in REGISTRY.collect()
        if family.name == "posemetry_pose_inference_seconds"
        for s in family.samples
        if s.name.endswith("_count")
    )
