"""Separate processes, as deployed: a `posemetry worker` subprocess, and `posemetry serve` driven over HTTP.

The serve tests configure an admin key (POSEMETRY_ADMIN_KEY) and send it, except the one about the first admin
key that serve generates and prints when none is configured.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
import redis
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from service.cli import QUEUE_NAMES
from service.queue import QUEUES, RedisDispatcher
from service.store import Frame
from tests.shared import TOWN_CENTRE, model_dir_path, require_dir
from tests.workers.conftest import IMAGE_SIZE, PEOPLE_PER_FRAME, simulated_camera, store_frames

REPO = Path(__file__).resolve().parents[2]
DEADLINE_S = 60.0
ADMIN_KEY = "serve-test-admin-key-0123456789abcdefghijklmnop"
TOKEN = re.compile(r"pm_[0-9a-f]{12}_[0-9A-Za-z]{43}")


def _wait_for(condition: Callable[[], bool], what: str, process: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + DEADLINE_S
    while not condition():
        if process.poll() is not None:
            raise AssertionError(f"process exited with {process.returncode} while waiting for {what}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def _stop(process: subprocess.Popen[bytes]) -> int:
    process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=30)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise


def test_queue_names_agree() -> None:
    # The CLI repeats the names so that `posemetry --help` does not import redis and rq.
    assert set(QUEUE_NAMES) == set(QUEUES)


def test_worker_subprocess_answers_stored_and_dispatched_frames(
    sessions: sessionmaker[Session], dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    store_frames(sessions, camera, 2)  # accepted while Redis was down: only the worker's start-up pass finds them
    store_frames(sessions, camera, 3, dispatcher=dispatcher)
    worker = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "worker", "--queue", "calibration", "--queue", "frames"],
        cwd=REPO,
        env=dict(os.environ),
    )

    def all_done() -> bool:
        with sessions() as session:
            return session.scalar(select(func.count()).where(Frame.status != "done")) == 0

    try:
        _wait_for(all_done, "every frame answered", worker)
    finally:
        returncode = _stop(worker)
    assert returncode == 0  # SIGTERM is a warm shutdown, not a crash
    assert dispatcher.calibration_state(camera.camera_id) == "idle"


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _serve_env(**settings: str) -> dict[str, str]:
    """This environment without any POSEMETRY_* (embedded mode), plus `settings` and the test's admin key."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("POSEMETRY_")}
    env["POSEMETRY_ADMIN_KEY"] = ADMIN_KEY
    env.update({f"POSEMETRY_{name.upper()}": value for name, value in settings.items()})
    return env


def _http(method: str, url: str, body: Any = None, token: str = ADMIN_KEY) -> tuple[int, Any]:
    data = None if body is None else json.dumps(body).encode()
    headers = {"content-type": "application/json", "authorization": f"Bearer {token}"}
    request = urllib.request.Request(url, data=data, method=method, headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, json.loads(response.read() or b"null")
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"null")


def test_serve_runs_everything_and_shuts_down_cleanly(
    tmp_path: Path, sessions: sessionmaker[Session], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Embedded mode: no Redis or database configured, everything lives in the data directory.
    env = _serve_env(calibration_min_people="30")
    data_dir = tmp_path / "serve"
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    serve = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(data_dir), "--port", str(port)],
        cwd=REPO,
        env=env,
    )
    try:
        _wait_for(lambda: _ready(base), "the API to be ready", serve)
        camera_settings = {"image_width_px": IMAGE_SIZE[0], "image_height_px": IMAGE_SIZE[1], "person_height_m": 1.7}
        status, _ = _http("PUT", f"{base}/v1/cameras/lobby", camera_settings)
        assert status == 201
        camera = simulated_camera(sessions)  # only its scene is used here
        urls = []
        for index in range(5):
            tops, bottoms = camera.frame_people()
            people = [
                {"shoulder": [float(t[0]), float(t[1])], "ankle": [float(b[0]), float(b[1])]}
                for t, b in zip(tops, bottoms, strict=True)
            ]
            frame = {"timestamp": f"2026-01-01T12:00:0{index}Z", "people": people}
            status, body = _http("POST", f"{base}/v1/cameras/lobby/keypoints", frame)
            assert status == 202, body
            urls.append(body["url"])

        def answered() -> bool:
            return all(_http("GET", f"{base}{url}")[1]["status"] == "done" for url in urls)

        _wait_for(answered, "every frame answered", serve)
        status, calibration = _http("GET", f"{base}/v1/cameras/lobby/calibration")
        assert status == 200 and calibration["status"] == "calibrated"
        # The simulated camera is recovered from 50 people (surveillance preset: 1.5 px noise, 7 cm height spread).
        scene = camera.scene
        assert abs(calibration["fx_px"] / scene.fx - 1) < 0.05
        normal = np.array(calibration["normal"])
        assert np.degrees(np.arccos(np.clip(normal @ scene.normal, -1, 1))) < 2.0
        # Every frame's distances against the truth, and its violations against the 6 ft threshold.
        errors, agree = [], []
        for k, url in enumerate(urls):
            result = _http("GET", f"{base}{url}")[1]["result"]
            truth = scene.points_bottom[k * PEOPLE_PER_FRAME : (k + 1) * PEOPLE_PER_FRAME]
            flagged = {(v["i"], v["j"]) for v in result["violations"]}
            for pair in result["pairs"]:
                true_m = float(np.linalg.norm(truth[pair["i"]] - truth[pair["j"]]))
                errors.append(abs(pair["distance_m"] / true_m - 1))
                if abs(true_m - 1.8288) > 0.3:  # clear of the threshold: the verdict must match the truth
                    agree.append(((pair["i"], pair["j"]) in flagged) == (true_m < 1.8288))
        assert np.median(errors) < 0.08
        assert np.mean(agree) > 0.95

        # A worker that dies is replaced.
        def workers() -> set[int]:
            alive = set()
            for child in psutil.Process(serve.pid).children():
                try:
                    if child.status() != psutil.STATUS_ZOMBIE and "workers.main" in " ".join(child.cmdline()):
                        alive.add(child.pid)
                except psutil.Error:
                    pass  # exited between listing and inspection
            return alive

        _wait_for(lambda: len(workers()) == 2, "two live workers", serve)
        before = workers()
        os.kill(min(before), signal.SIGKILL)
        _wait_for(lambda: len(workers() - before) == 1 and len(workers()) == 2, "a replacement worker", serve)
    finally:
        returncode = _stop(serve)
    assert returncode == 0
    assert (data_dir / "posemetry.sqlite3").is_file()
    assert not (data_dir / "redis" / "redis.sock").exists()  # the embedded Redis was shut down


def test_serve_finds_people_in_posted_images(tmp_path: Path) -> None:
    """Image frames end to end: JPEGs over HTTP, real ONNX pose in a worker, detections and an overlay back."""
    frames = sorted((require_dir(TOWN_CENTRE, "Town Centre data") / "frames").glob("clip_*.jpg"))[:3]
    env = _serve_env(model_dir=str(require_dir(model_dir_path(), "pose model")))
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    serve = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(tmp_path / "serve"), "--port", str(port)],
        cwd=REPO,
        env=env,
    )
    try:
        _wait_for(lambda: _ready(base), "the API to be ready", serve)
        settings = {"image_width_px": 1920, "image_height_px": 1080, "keep_images": True}
        assert _http("PUT", f"{base}/v1/cameras/street", settings)[0] == 201
        urls = []
        for index, path in enumerate(frames):
            request = urllib.request.Request(
                f"{base}/v1/cameras/street/frames?frame_id=clip-{index}",
                data=path.read_bytes(),
                method="POST",
                headers={"content-type": "image/jpeg", "authorization": f"Bearer {ADMIN_KEY}"},
            )
            with urllib.request.urlopen(request, timeout=10) as response:
                assert response.status == 202
                urls.append(json.loads(response.read())["url"])

        def detected() -> bool:
            return all(_http("GET", f"{base}{url}")[1]["status"] != "detecting" for url in urls)

        _wait_for(detected, "pose on every image", serve)
        for url in urls:
            frame = _http("GET", f"{base}{url}")[1]
            assert frame["source"] == "image" and frame["pose_model"].startswith("rtmdet-nano")
            assert frame["people"] == len(frame["detections"]) >= 8
            assert sum(d["usable"] for d in frame["detections"]) >= 4
            overlay = urllib.request.Request(
                f"{base}{frame['links']['overlay']}", headers={"authorization": f"Bearer {ADMIN_KEY}"}
            )
            with urllib.request.urlopen(overlay, timeout=30) as response:
                assert response.headers["content-type"] == "image/png"
                assert response.read().startswith(b"\x89PNG")
    finally:
        assert _stop(serve) == 0


def test_serve_prints_a_first_admin_key_once(tmp_path: Path) -> None:
    """No POSEMETRY_ADMIN_KEY: the first start makes an admin key and prints it; later starts print none."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("POSEMETRY_")}
    data_dir = tmp_path / "serve"
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    command = [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(data_dir), "--port", str(port)]
    command += ["--workers", "1"]
    outputs = []
    for start in range(2):
        log_path = tmp_path / f"serve-{start}.log"
        with log_path.open("wb") as log:
            serve = subprocess.Popen(command, cwd=REPO, env=env, stdout=log, stderr=log)
        try:
            _wait_for(lambda: _ready(base), "the API to be ready", serve)
            assert _http("GET", f"{base}/v1/cameras", token="")[0] == 401
            output = log_path.read_text()
            outputs.append(output)
            if start == 0:
                tokens = TOKEN.findall(output)
                assert len(tokens) == 1, output
                (first_admin,) = tokens
                assert "First admin API key" in output and "shown this once" in output
                status, created = _http("POST", f"{base}/v1/keys", {"name": "lobby", "cameras": ["lobby"]}, first_admin)
                assert status == 201, created
                scoped = created["token"]
            # The first admin key and the key it made work on every start.
            status, listed = _http("GET", f"{base}/v1/keys", token=first_admin)
            assert status == 200 and {k["name"] for k in listed["items"]} == {
                "first admin key (posemetry serve)",
                "lobby",
            }
            assert _http("GET", f"{base}/v1/cameras", token=scoped)[0] == 200
            assert _http("GET", f"{base}/v1/keys", token=scoped)[0] == 403
        finally:
            assert _stop(serve) == 0
    assert TOKEN.search(outputs[1]) is None and "First admin API key" not in outputs[1]
    for database_file in data_dir.glob("posemetry.sqlite3*"):  # the database and its WAL: only a hash is stored
        assert first_admin.encode() not in database_file.read_bytes()


def _ready(base: str) -> bool:
    try:
        return _http("GET", f"{base}/readyz")[0] == 200
    except OSError:
        return False
