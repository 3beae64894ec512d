"""What the fault tests break and watch: real redis-server, `posemetry api` and `posemetry worker` processes, the
jobs RQ is running and the worker process that runs each.

Nothing here fakes a fault: a killed worker is a SIGKILLed process, a dead Redis a SIGKILLed redis-server, a
database outage a stopped PostgreSQL. The tests find the moment to strike by watching what a user's operator
would: RQ's StartedJobRegistry names the job that is running, its execution names the worker, the worker's
registration names its process id.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import redis
from rq import Worker
from rq.executions import Execution
from rq.registry import StartedJobRegistry

from bench.simulate import Scene, SceneConfig, draw_scene
from service.embedded_redis import redis_server_binary
from service.http.problems import PROBLEM_MEDIA_TYPE
from service.store.migrate import upgrade
from tests.support.jobs import FRAME_SPACING_S
from tests.support.postgres import PostgresCluster, cluster_or_skip
from tests.support.serving import REPO, clean_environment, free_port, stop
from tests.support.shared import model_dir_path

# Generous: a loaded two-core CI machine runs these next to everything else.
DEADLINE_S = 90.0
POLL_S = 0.05
START = datetime(2026, 5, 1, 9, 0, tzinfo=UTC)


def wait_until(condition: Callable[[], Any], what: str, timeout_s: float = DEADLINE_S, poll_s: float = POLL_S) -> Any:
    """Poll until `condition()` is truthy (and return it); fail naming `what` after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(poll_s)


# --------------------------------------------------------------------------------------------------- HTTP


@dataclass(frozen=True)
class Answer:
    status: int
    headers: dict[str, str]
    body: Any

    @property
    def is_problem(self) -> bool:
        """An RFC 9457 problem document whose status matches the response's."""
        return (
            self.headers.get("content-type", "").startswith(PROBLEM_MEDIA_TYPE)
            and isinstance(self.body, dict)
            and self.body.get("status") == self.status
        )


@dataclass
class Client:
    """A camera system or dashboard talking to the API with a key."""

    base: str
    api_key: str

    def request(self, method: str, path: str, body: Any = None, timeout_s: float = 30.0) -> Answer:
        data = None if body is None else json.dumps(body).encode()
        headers = {"authorization": f"Bearer {self.api_key}"}
        if data is not None:
            headers["content-type"] = "application/json"
        request = urllib.request.Request(f"{self.base}{path}", data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(request, timeout=timeout_s) as response:
                return _answer(response.status, response.headers, response.read())
        except urllib.error.HTTPError as exc:
            return _answer(exc.code, exc.headers, exc.read())

    def post_image(self, camera_id: str, image: bytes, frame_id: str) -> Answer:
        request = urllib.request.Request(
            f"{self.base}/v1/cameras/{camera_id}/frames?frame_id={frame_id}",
            data=image,
            method="POST",
            headers={"authorization": f"Bearer {self.api_key}", "content-type": "image/jpeg"},
        )
        try:
            with urllib.request.urlopen(request, timeout=60) as response:
                return _answer(response.status, response.headers, response.read())
        except urllib.error.HTTPError as exc:
            return _answer(exc.code, exc.headers, exc.read())

    def get(self, path: str) -> Any:
        answer = self.request("GET", path)
        assert answer.status == 200, (path, answer)
        return answer.body

    def ready(self) -> bool:
        try:
            return self.request("GET", "/readyz", timeout_s=5).status == 200
        except OSError:
            return False


def _answer(status: int, raw_headers: Any, content: bytes) -> Answer:
    """JSON bodies decoded, others (the metrics exposition) as text."""
    headers = {key.lower(): value for key, value in raw_headers.items()}
    if "json" in headers.get("content-type", ""):
        return Answer(status, headers, json.loads(content) if content else None)
    return Answer(status, headers, content.decode(errors="replace"))


# --------------------------------------------------------------------------------------------------- cameras


class SceneExhaustedError(RuntimeError):
    """A simulated camera was asked for a frame past the last one its scene has people for.

    Handing out an empty frame instead would post a frame with nobody in it: measured `done` with no pair and no
    violation, so a test that expects one webhook event per measured frame would read it as an event lost. That is
    how the Redis-restart fault test once failed (400 events for 411 measured frames: the fleet had posted past the
    400 frames of its alarm camera's scene), and only on runs fast enough to post that many.
    """


@dataclass
class SimulatedCamera:
    """A camera's truth and a supply of people to post, one frame at a time."""

    camera_id: str
    scene: Scene
    people_per_frame: int
    posted: int = 0
    frame_ids: list[str] = field(default_factory=list)

    @classmethod
    def draw(cls, camera_id: str, frames: int, people_per_frame: int, seed: int = 5) -> SimulatedCamera:
        config = SceneConfig.surveillance(n_people=frames * people_per_frame)
        return cls(camera_id, draw_scene(config, np.random.default_rng(seed)), people_per_frame)

    def settings(self) -> dict[str, Any]:
        width, height = self.scene.image_size
        return {"image_width_px": width, "image_height_px": height, "person_height_m": 1.7}

    @property
    def frames(self) -> int:
        """How many frames the scene has people for."""
        return len(self.scene.tops_px) // self.people_per_frame

    def next_frame(self) -> dict[str, Any]:
        """The next frame's body, with a client frame id (so a retry is the same frame); SceneExhaustedError once
        the scene's people are all posted (never a frame with fewer people, which a test would count as measured
        without the violations it expects)."""
        k = self.posted
        if k >= self.frames:
            raise SceneExhaustedError(
                f"camera {self.camera_id} has posted all {self.frames} frames its scene has people for: draw it "
                "with more frames"
            )
        people = slice(k * self.people_per_frame, (k + 1) * self.people_per_frame)
        self.posted += 1
        frame_id = f"{self.camera_id}-{k}"
        self.frame_ids.append(frame_id)
        return {
            "timestamp": (START + timedelta(seconds=FRAME_SPACING_S * k)).isoformat(),
            "frame_id": frame_id,
            "people": [
                {"shoulder": [float(t[0]), float(t[1])], "ankle": [float(b[0]), float(b[1])]}
                for t, b in zip(self.scene.tops_px[people], self.scene.bottoms_px[people], strict=True)
            ],
        }


def create_camera(client: Client, camera: SimulatedCamera) -> None:
    answer = client.request("PUT", f"/v1/cameras/{camera.camera_id}", camera.settings())
    assert answer.status == 201, answer


def post_frames(client: Client, camera: SimulatedCamera, frames: int) -> list[str]:
    """Post frames while everything is up; returns the frames' URLs."""
    urls = []
    for _ in range(frames):
        answer = client.request("POST", f"/v1/cameras/{camera.camera_id}/keypoints", camera.next_frame())
        assert answer.status == 202, answer
        urls.append(answer.body["url"])
    return urls


def post_until_accepted(client: Client, camera: SimulatedCamera, refusals: list[Answer]) -> Answer:
    """Post the camera's next frame as a well-behaved client does: on 503, wait and send the same frame again."""
    body = camera.next_frame()
    while True:
        answer = client.request("POST", f"/v1/cameras/{camera.camera_id}/keypoints", body)
        if answer.status != 503:
            assert answer.status in (200, 202), answer
            return answer
        refusals.append(answer)
        time.sleep(0.2)


# --------------------------------------------------------------------------------------------------- RQ


def started_job(connection: redis.Redis, queue: str, job_id: str | None = None) -> tuple[str, str] | None:
    """(job id, execution id) of a job of `queue` that RQ has started (`job_id`: that one only), else None.

    Read without cleanup: this only watches, it must not change what RQ's maintenance will find.
    """
    registry = StartedJobRegistry(queue, connection=connection)
    for found_id, execution_id in registry.get_job_and_execution_ids(cleanup=False):
        if job_id is None or found_id == job_id:
            return found_id, execution_id
    return None


def worker_pid(connection: redis.Redis, job_id: str, execution_id: str) -> int | None:
    """The process running a job's execution (a SimpleWorker runs its jobs in its own process); None when the
    execution ended between being listed and being read (a frames job takes milliseconds)."""
    try:
        execution = Execution.fetch(execution_id, job_id, connection=connection)
    except ValueError:  # "Execution ... not found in Redis"
        return None
    worker = Worker.find_by_key(Worker.redis_worker_namespace_prefix + execution.worker_name, connection=connection)
    assert worker is not None and worker.pid, f"no live worker registration for {execution.worker_name}"
    return worker.pid


def kill_worker_running(connection: redis.Redis, queue: str, job_id: str | None = None) -> tuple[str, int, float]:
    """SIGKILL the worker process as soon as RQ has started a job of `queue`; (job id, pid, time of the kill)."""

    def running() -> tuple[str, int] | None:
        found = started_job(connection, queue, job_id)
        pid = None if found is None else worker_pid(connection, *found)
        return None if found is None or pid is None else (found[0], pid)

    # Polled fast: the kill must land while the job still works.
    found_id, pid = wait_until(running, f"a started {queue} job", poll_s=0.005)
    os.kill(pid, signal.SIGKILL)
    return found_id, pid, time.monotonic()


# --------------------------------------------------------------------------------------------------- processes


class RedisServer:
    """A standalone redis-server on a unix socket, as Compose's `redis` service would be, without persistence:
    once killed and started again it comes back empty, the hardest case for the service."""

    def __init__(self) -> None:
        # Under /tmp: a pytest tmp_path would overflow the ~107-byte limit on unix socket paths.
        self.directory = Path(tempfile.mkdtemp(prefix="pm-redis-"))
        self.socket = self.directory / "redis.sock"
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"unix://{self.socket}"

    def start(self) -> RedisServer:
        command = [redis_server_binary(), "--port", "0", "--unixsocket", str(self.socket), "--save", ""]
        command += ["--appendonly", "no", "--dir", str(self.directory), "--logfile", str(self.directory / "log")]
        self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL)
        client = redis.Redis(unix_socket_path=str(self.socket))
        wait_until(lambda: _pings(client), "redis-server to answer", timeout_s=30)
        client.close()
        return self

    def kill(self) -> None:
        assert self.process is not None
        self.process.kill()
        self.process.wait()

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=10)
        for path in self.directory.iterdir():
            path.unlink()
        self.directory.rmdir()


def _pings(client: redis.Redis) -> bool:
    try:
        return bool(client.ping())
    except (redis.ConnectionError, redis.TimeoutError, OSError):
        return False


def posemetry(args: list[str], env: dict[str, str]) -> subprocess.Popen[bytes]:
    """A `posemetry` command as its own process, as a supervisor (Compose, systemd) would run it."""
    return subprocess.Popen([sys.executable, "-m", "service.cli", *args], cwd=REPO, env=env)


@contextmanager
def running(process: subprocess.Popen[bytes]) -> Iterator[subprocess.Popen[bytes]]:
    """Stop the process afterwards (SIGTERM, as a supervisor would; killed if it does not go)."""
    try:
        yield process
    finally:
        stop(process)


def api_process(env: dict[str, str]) -> tuple[subprocess.Popen[bytes], str]:
    port = free_port()
    return posemetry(["api", "--port", str(port)], env), f"http://127.0.0.1:{port}"


class Supervised:
    """A process that is started again whenever it exits, as Compose's `restart: unless-stopped` does (every
    RESTART_POLL_S); `pause()` holds restarts back, to show that the others cope without it."""

    RESTART_POLL_S = 0.5

    def __init__(self, start: Callable[[], subprocess.Popen[bytes]]) -> None:
        import threading

        self._start = start
        self.process = start()
        self.restarts = 0
        self.paused = False
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stopping.wait(self.RESTART_POLL_S):
            if not self.paused and self.process.poll() is not None:
                self.process = self._start()
                self.restarts += 1

    def pause(self) -> None:
        self.paused = True

    def resume(self) -> None:
        self.paused = False

    def stop(self) -> None:
        self._stopping.set()
        self._thread.join()
        with running(self.process):
            pass


# --------------------------------------------------------------------------------------------------- Compose


@dataclass
class Stack:
    """The Compose deployment, process by process: PostgreSQL, a redis-server, `posemetry api` and two supervised
    `posemetry worker` processes."""

    cluster: PostgresCluster
    database_url: str
    redis: RedisServer
    api: subprocess.Popen[bytes]
    client: Client
    workers: list[Supervised]
    queue_redis: redis.Redis


@contextmanager
def compose_stack(**settings: str) -> Iterator[Stack]:
    """Start the stack as Compose would (migrate first), with `settings` (names without the prefix) on top of
    cameras that calibrate only when a test forces a solve; the API must survive whatever the test does."""
    cluster = cluster_or_skip()
    cluster.start()
    redis_server = RedisServer().start()
    try:
        url = cluster.create_database("posemetry")
        upgrade(url)  # Compose's `migrate` service
        env = clean_environment(
            database_url=url,
            redis_url=redis_server.url,
            calibration_min_people=str(10**9),
            model_dir=str(model_dir_path()),
            **settings,
        )
        api, base = api_process(env)
        workers = [Supervised(lambda: posemetry(["worker"], env)) for _ in range(2)]
        with running(api):
            client = Client(base, env["POSEMETRY_ADMIN_KEY"])
            wait_until(client.ready, "the API to be ready")
            queue_redis = redis.Redis(unix_socket_path=str(redis_server.socket))
            try:
                yield Stack(cluster, url, redis_server, api, client, workers, queue_redis)
            finally:
                queue_redis.close()
                for worker in workers:
                    worker.stop()
            assert api.poll() is None, "the API process died"
    finally:
        redis_server.stop()
        cluster.stop()
