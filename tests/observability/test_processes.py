"""Metrics and request ids across real processes: `posemetry serve` (two API processes and a worker sharing one
metrics directory) and a standalone forking worker serving its own metrics port."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from service.queue import CALIBRATION_QUEUE, FRAMES_QUEUE, POSE_QUEUE, QUEUES, RedisDispatcher
from service.store import Frame
from tests.support.jobs import IMAGE_SIZE, frame_timestamp, simulated_camera, store_frames, store_image
from tests.support.scrape import Scrape
from tests.support.serving import REPO, Served, clean_environment, free_port, serve, stop, wait_for
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir


def _scrape(app: Served) -> Scrape:
    status, body, _type = app.raw("GET", "/metrics")
    assert status == 200
    return Scrape(body.decode())


def _pids_with_files(directory: Path) -> set[str]:
    return {match.group(1) for f in directory.glob("*.db") if (match := re.search(r"_(\d+(?:-horse)?)\.db$", f.name))}


def test_serve_exports_every_process_and_logs_json_under_request_ids(
    tmp_path: Path, sessions: sessionmaker[Session]
) -> None:
    data_dir = tmp_path / "serve"
    stale = data_dir / "metrics" / "counter_4242.db"  # left by an earlier run: must not be added to this one's
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"\0" * 64)
    log_path = tmp_path / "serve.log"
    args = ["--api-processes", "2", "--workers", "1", "--log-format", "json"]
    posted: dict[str, str] = {}
    with serve(data_dir, clean_environment(calibration_min_people="30"), args, output=log_path) as app:
        assert not stale.exists()
        camera_settings = {"image_width_px": IMAGE_SIZE[0], "image_height_px": IMAGE_SIZE[1], "person_height_m": 1.7}
        assert app.http("PUT", "/v1/cameras/lobby", camera_settings)[0] == 201
        scene = simulated_camera(sessions)  # only its people are used
        for index in range(5):
            tops, bottoms = scene.frame_people()
            people = [{"shoulder": t.tolist(), "ankle": b.tolist()} for t, b in zip(tops, bottoms, strict=True)]
            frame = {"timestamp": frame_timestamp(index), "people": people}
            status, body = app.http(
                "POST", "/v1/cameras/lobby/keypoints", frame, headers={"X-Request-ID": f"serve-req-{index}"}
            )
            assert status == 202, body
            posted[body["frame_id"]] = f"serve-req-{index}"
        app.wait_for(
            lambda: all(app.http("GET", f"/v1/cameras/lobby/frames/{f}")[1]["status"] == "done" for f in posted),
            "every frame answered",
        )
        # Each scrape reaches one of the two API processes; each must answer for all processes.
        for _ in range(4):
            metrics = _scrape(app)
            posts = metrics.value(
                "posemetry_http_request_duration_seconds_count",
                route="/v1/cameras/{camera_id}/keypoints",
                method="POST",
                status_class="2xx",
            )
            assert posts == 5
            assert metrics.value("posemetry_frames_ingested_total", source="keypoints") == 5
            # Recorded by the worker process only.
            assert metrics.value("posemetry_job_duration_seconds_count", queue=FRAMES_QUEUE, outcome="succeeded") >= 1
            solves = metrics.value("posemetry_job_duration_seconds_count", queue=CALIBRATION_QUEUE, outcome="succeeded")
            assert solves >= 1
            assert metrics.value("posemetry_camera_calibrated", camera="lobby") == 1
            evidence = app.http("GET", "/v1/cameras/lobby")[1]["usable_evidence_count"]
            assert metrics.value("posemetry_camera_usable_evidence", camera="lobby") == evidence > 40
            assert metrics.value("posemetry_queue_jobs", queue=FRAMES_QUEUE, state="queued") is not None
            assert metrics.value("posemetry_metrics_source_up", source="redis") == 1
            assert metrics.value("posemetry_http_requests_in_progress") >= 1  # this scrape
        # Two API processes and the worker each write their own files.
        assert len(_pids_with_files(data_dir / "metrics")) >= 3
        assert app.stop() == 0
    lines = [json.loads(line) for line in log_path.read_text().splitlines()]  # every line of every process is JSON
    access = {line["request_id"]: line for line in lines if line["logger"] == "posemetry.access"}
    measured = {line["frame_id"]: line for line in lines if line["logger"] == "workers.jobs" and "frame_id" in line}
    for frame_id, request_id in posted.items():
        assert access[request_id]["status"] == 202 and access[request_id]["camera_id"] == "lobby"
        # The frame's line from the worker process carries the id the client sent to an API process.
        assert measured[frame_id]["request_id"] == request_id
        assert measured[frame_id]["pid"] != access[request_id]["pid"]


def test_a_standalone_forking_worker_serves_its_own_metrics(
    tmp_path: Path, sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher
) -> None:
    jpeg = (require_dir(TOWN_CENTRE, "Town Centre data") / "frames" / "clip_000000.jpg").read_bytes()
    require_dir(model_dir_path(), "pose model")
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 4, dispatcher=redis_dispatcher)
    image_frame = store_image(sessions, jpeg)
    redis_dispatcher.image_stored("town", image_frame)
    metrics_dir = tmp_path / "worker-metrics"
    metrics_dir.mkdir()
    port = free_port()
    env = {**os.environ, "PROMETHEUS_MULTIPROC_DIR": str(metrics_dir)}
    queues = [arg for queue in QUEUES for arg in ("--queue", queue)]
    command = [sys.executable, "-m", "service.cli", "worker", *queues, "--fork", "--metrics-port", str(port)]
    worker = subprocess.Popen(command, cwd=REPO, env=env, stderr=subprocess.DEVNULL)

    def all_done() -> bool:
        # The image's camera is not calibrated: its frame goes from detecting to pending, and stays there.
        with sessions() as session:
            waiting = select(func.count()).where(Frame.status != "done", Frame.id != image_frame)
            return session.scalar(waiting) == 0 and session.get(Frame, image_frame).status == "pending"

    def jobs_recorded(metrics: Scrape) -> tuple[float, float]:
        frames = metrics.value("posemetry_job_duration_seconds_count", queue=FRAMES_QUEUE, outcome="succeeded")
        pose = metrics.value("posemetry_job_duration_seconds_count", queue=POSE_QUEUE, outcome="succeeded")
        return frames, pose

    try:
        wait_for(worker, all_done, "every frame answered")
        # A job's duration is recorded as it ends, after its frames are committed: the last one may still be ending.
        deadline = time.monotonic() + 30
        metrics = _eventually(lambda: _scrape_port(port), worker)
        while jobs_recorded(metrics)[0] < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
            metrics = _scrape_port(port)
    finally:
        assert stop(worker) == 0
    frames_jobs, pose_jobs = jobs_recorded(metrics)
    assert frames_jobs >= 2 and pose_jobs == 1
    assert metrics.value("posemetry_job_failures_total", queue=POSE_QUEUE) == 0
    # Recorded inside the forked job process, and still on the worker's port.
    inference = [s for s in metrics.samples if s.name == "posemetry_pose_inference_seconds_count"]
    assert [s.value for s in inference] == [1.0] and inference[0].labels["model"].startswith("rtmdet-nano")
    # Every job ran in a process of its own, yet their files are one set per worker, not one per job.
    assert _pids_with_files(metrics_dir) == {str(worker.pid), f"{worker.pid}-horse"}


def _scrape_port(port: int) -> Scrape:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as response:
        assert response.status == 200
        return Scrape(response.read().decode())


def _eventually(scrape: Callable[[], Scrape], process: subprocess.Popen[bytes]) -> Scrape:
    """The metrics port answers once the worker has started it; retry until then."""
    deadline = time.monotonic() + 30
    while True:
        try:
            return scrape()
        except OSError:
            if time.monotonic() > deadline or process.poll() is not None:
                raise
            time.sleep(0.2)


def test_a_worker_given_only_a_metrics_port_keeps_its_metrics_in_a_directory_of_its_own(
    sessions: sessionmaker[Session], dispatcher: RedisDispatcher
) -> None:
    """As in a container of docker-compose.yml: POSEMETRY_WORKER_METRICS_PORT set and no metrics directory given."""
    store_frames(sessions, simulated_camera(sessions), 5, dispatcher=dispatcher)
    port = free_port()
    env = {name: value for name, value in os.environ.items() if name != "PROMETHEUS_MULTIPROC_DIR"}
    env["POSEMETRY_WORKER_METRICS_PORT"] = str(port)
    queues = [arg for queue in QUEUES for arg in ("--queue", queue)]
    command = [sys.executable, "-m", "service.cli", "worker", *queues, "--fork"]
    worker = subprocess.Popen(command, cwd=REPO, env=env, stderr=subprocess.DEVNULL)

    def all_done() -> bool:
        with sessions() as session:
            return session.scalar(select(func.count()).where(Frame.status != "done")) == 0

    try:
        wait_for(worker, all_done, "every frame measured")

        def measuring_recorded() -> bool:
            # A job's duration is recorded as it ends, just after its frames are committed as done.
            scrape = _eventually(lambda: _scrape_port(port), worker)
            count = scrape.value("posemetry_job_duration_seconds_count", queue=FRAMES_QUEUE, outcome="succeeded")
            return count is not None and count >= 1

        # Recorded in the forked job processes, and still on the worker's port.
        wait_for(worker, measuring_recorded, "the measuring job's duration on the worker's metrics port")
    finally:
        assert stop(worker) == 0
