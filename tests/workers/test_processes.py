"""Separate processes, as deployed: a `posemetry worker` subprocess, and `posemetry serve` driven over HTTP.

The serve tests configure an admin key (POSEMETRY_ADMIN_KEY, tests/serving.py) and send it, except the one about
the first admin key that serve generates and prints when none is configured.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import redis
from rq import Queue, Retry
from rq.job import Job, JobStatus
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from service.cli.processes import QUEUE_NAMES
from service.domain import POSTURES
from service.queue import FRAMES_QUEUE, QUEUES, RedisDispatcher
from service.runtime import default_process_split
from service.store import Frame
from tests.support.jobs import IMAGE_SIZE, frame_timestamp, simulated_camera, store_frames
from tests.support.serving import REPO, clean_environment, serve, stop, wait_for
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir
from workers.main import OVERRUN_EXIT_STATUS

TOKEN = re.compile(r"pm_[0-9a-f]{12}_[0-9A-Za-z]{43}")


def test_queue_names_agree() -> None:
    # The CLI repeats the names so that `posemetry --help` does not import redis and rq.
    assert QUEUE_NAMES == QUEUES  # the order too: a worker serves the first queue with work


def test_worker_subprocess_answers_stored_and_dispatched_frames(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 2)  # accepted while Redis was down: only the worker's start-up pass finds them
    store_frames(sessions, camera, 3, dispatcher=redis_dispatcher)
    worker = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "worker", "--queue", "calibration", "--queue", "frames"],
        cwd=REPO,
        env=dict(os.environ),
    )

    def all_done() -> bool:
        with sessions() as session:
            return session.scalar(select(func.count()).where(Frame.status != "done")) == 0

    try:
        wait_for(worker, all_done, "every frame answered")
    finally:
        returncode = stop(worker)
    assert returncode == 0  # SIGTERM is a warm shutdown, not a crash
    assert redis_dispatcher.calibration_state(camera.camera_id) == "idle"


def overrunning_job() -> None:
    """A job that never comes back: it waits on a thread that works for ten minutes (what a library deadlocked in
    a worker's thread leaves behind)."""
    stuck = threading.Thread(target=time.sleep, args=(600,))
    stuck.start()
    stuck.join()


def test_a_worker_leaves_after_a_job_overruns_its_timeout_and_the_job_is_retried(
    sessions: sessionmaker[Session], connection: redis.Redis
) -> None:
    """The stuck thread would block every later job that needs it and an ordinary exit: the worker exits at once
    with its overrun status, and the job waits, queued again, for the fresh worker its supervisor starts."""
    worker = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "worker", "--queue", FRAMES_QUEUE], cwd=REPO, env=dict(os.environ)
    )
    job = Queue(FRAMES_QUEUE, connection=connection).enqueue(overrunning_job, job_timeout=2, retry=Retry(max=1))
    try:
        returncode = worker.wait(timeout=60)
    finally:
        if worker.poll() is None:
            worker.kill()
            worker.wait()
    assert returncode == OVERRUN_EXIT_STATUS
    stored = Job.fetch(job.id, connection=connection)
    assert stored.get_status() == JobStatus.QUEUED and stored.retries_left == 0


def test_serve_runs_everything_and_shuts_down_cleanly(tmp_path: Path, sessions: sessionmaker[Session]) -> None:
    """Embedded mode: no Redis or database configured, everything lives in the data directory; a worker that dies
    is replaced; Ctrl-C (SIGTERM) stops the API, the workers and the embedded Redis. (What the service answers is
    checked end to end in tests/e2e.)"""
    data_dir = tmp_path / "serve"
    with serve(data_dir, clean_environment(calibration_min_people="30")) as app:
        camera_settings = {"image_width_px": IMAGE_SIZE[0], "image_height_px": IMAGE_SIZE[1], "person_height_m": 1.7}
        assert app.http("PUT", "/v1/cameras/lobby", camera_settings)[0] == 201
        camera = simulated_camera(sessions)  # only its scene is used here
        urls = []
        for index in range(5):
            tops, bottoms = camera.frame_people()
            people = [
                {"shoulder": [float(t[0]), float(t[1])], "ankle": [float(b[0]), float(b[1])]}
                for t, b in zip(tops, bottoms, strict=True)
            ]
            status, body = app.http(
                "POST", "/v1/cameras/lobby/keypoints", {"timestamp": frame_timestamp(index), "people": people}
            )
            assert status == 202, body
            urls.append(body["url"])
        app.wait_for(lambda: all(app.http("GET", url)[1]["status"] == "done" for url in urls), "every frame answered")
        assert app.http("GET", "/v1/cameras/lobby/calibration")[1]["status"] == "calibrated"

        def workers() -> set[int]:
            return app.children("workers.main")

        _, count = default_process_split()  # serve's default on this machine (at least one)
        app.wait_for(lambda: len(workers()) == count, f"{count} live workers")
        before = workers()
        os.kill(min(before), signal.SIGKILL)
        app.wait_for(lambda: len(workers() - before) == 1 and len(workers()) == count, "a replacement worker")
        assert app.stop() == 0
    assert (data_dir / "posemetry.sqlite3").is_file()
    assert not (data_dir / "redis" / "redis.sock").exists()  # the embedded Redis was shut down


def test_serve_finds_people_in_posted_images(tmp_path: Path) -> None:
    """Image frames end to end: JPEGs over HTTP, real ONNX pose in a worker, detections and an overlay back."""
    frames = sorted((require_dir(TOWN_CENTRE, "Town Centre data") / "frames").glob("clip_*.jpg"))[:3]
    env = clean_environment(model_dir=str(require_dir(model_dir_path(), "pose model")))
    with serve(tmp_path / "serve", env) as app:
        settings = {"image_width_px": 1920, "image_height_px": 1080, "keep_images": True}
        assert app.http("PUT", "/v1/cameras/street", settings)[0] == 201
        urls = []
        for index, path in enumerate(frames):
            status, body, _type = app.raw(
                "POST", f"/v1/cameras/street/frames?frame_id=clip-{index}", path.read_bytes(), "image/jpeg"
            )
            assert status == 202, body
            urls.append(json.loads(body)["url"])
        app.wait_for(
            lambda: all(app.http("GET", url)[1]["status"] != "detecting" for url in urls), "pose on every image"
        )
        for url in urls:
            frame = app.http("GET", url)[1]
            assert frame["source"] == "image" and frame["pose_model"].startswith("rtmdet-nano")
            assert frame["people"] == len(frame["detections"]) >= 8
            assert sum(d["usable"] for d in frame["detections"]) >= 4
            # The pose's verdict on each person: every usable one stands.
            assert {d["posture"] for d in frame["detections"]} <= set(POSTURES)
            assert all(d["posture"] == "standing" for d in frame["detections"] if d["usable"])
            status, png, content_type = app.raw("GET", frame["links"]["overlay"])
            assert status == 200 and content_type == "image/png" and png.startswith(b"\x89PNG")
        assert app.stop() == 0


def test_serve_prints_a_first_admin_key_once(tmp_path: Path) -> None:
    """No POSEMETRY_ADMIN_KEY: the first start makes an admin key and prints it; later starts print none."""
    env = clean_environment()
    del env["POSEMETRY_ADMIN_KEY"]
    data_dir = tmp_path / "serve"
    outputs = []
    for start in range(2):
        log_path = tmp_path / f"serve-{start}.log"
        with serve(data_dir, env, ["--workers", "1"], output=log_path) as app:
            assert app.http("GET", "/v1/cameras", token="")[0] == 401
            output = log_path.read_text()
            outputs.append(output)
            if start == 0:
                tokens = TOKEN.findall(output)
                assert len(tokens) == 1, output
                (first_admin,) = tokens
                assert "First admin API key" in output and "shown this once" in output
                status, created = app.http("POST", "/v1/keys", {"name": "lobby", "cameras": ["lobby"]}, first_admin)
                assert status == 201, created
                scoped = created["token"]
            # The first admin key and the key it made work on every start.
            status, listed = app.http("GET", "/v1/keys", token=first_admin)
            assert status == 200 and {k["name"] for k in listed["items"]} == {
                "first admin key (posemetry serve)",
                "lobby",
            }
            assert app.http("GET", "/v1/cameras", token=scoped)[0] == 200
            assert app.http("GET", "/v1/keys", token=scoped)[0] == 403
            assert app.stop() == 0
    assert TOKEN.search(outputs[1]) is None and "First admin API key" not in outputs[1]
    for database_file in data_dir.glob("posemetry.sqlite3*"):  # the database and its WAL: only a hash is stored
        assert first_admin.encode() not in database_file.read_bytes()
