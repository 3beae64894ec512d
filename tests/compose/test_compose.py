"""The production path, run for real: the image built from the Dockerfile, docker-compose.yml brought up, and the stack
used over HTTP as an operator and a camera system would, through a worker killed mid-job and a database restart.

Where the public base images cannot be pulled, tests/compose/standins/build.sh puts local stand-ins under their
names first (see README, "Deployment with Docker Compose"). The posemetry image is built as README documents for
machines that have the model files: `docker build --build-context models=DIR`. Rows are counted in PostgreSQL
itself (psql in its container) after the faults: nothing accepted may be lost, nothing may be stored twice.
"""

from __future__ import annotations

import functools
import select
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from alembic.script import ScriptDirectory

from bench.simulate import SceneConfig, draw_scene
from service.store.migrate import alembic_config
from tests.compose.stack import (
    DEADLINE_S,
    Answer,
    Phases,
    Stack,
    build_image,
    ensure_base_images,
    require_docker,
    run,
    wait_until,
)
from tests.support.app import coco_person
from tests.support.jobs import FRAME_SPACING_S
from tests.support.serving import free_port
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir

PROJECT = "posemetry-compose-test"
FRAMES = 12  # keypoint frames of PEOPLE people: 120 people, four solves (at 30, 45, 68 and 102)
PEOPLE = 10
IMAGES = 9  # Town Centre frames for three pose workers, one of which is killed mid-job
START = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)
# Run in the API's container (the same image, never killed here), with RQ's public API: says "watching" once it
# reaches Redis, then waits for a pose worker with a job in hand and prints its host name (its container's id) and
# the job's id; the one whose job started last, so that it has the most left to do. Host names given as arguments
# are skipped: a killed worker stays registered, with its job, for a while.
FIND_BUSY_POSE_WORKER = """
import os, sys, time
import redis, rq
connection = redis.Redis.from_url(os.environ["POSEMETRY_REDIS_URL"])
queue = rq.Queue("pose", connection=connection)
rq.Worker.all(queue=queue)
print("watching", flush=True)
deadline = time.monotonic() + 60
while time.monotonic() < deadline:
    busy = []
    for worker in rq.Worker.all(queue=queue):
        execution = worker.execution
        if execution is not None and worker.hostname not in sys.argv[1:]:
            busy.append((execution.created_at, worker.hostname, execution.job_id))
    if busy:
        sys.exit(print(*max(busy)[1:]))
    time.sleep(0.05)
sys.exit("no pose worker had a job in hand for 60 s")
"""


def test_the_compose_stack_measures_scales_and_loses_nothing_to_a_killed_worker_or_a_database_restart(
    capsys: pytest.CaptureFixture[str],
) -> None:
    require_docker()
    models = require_dir(model_dir_path(), "pose model")
    town_frames = sorted(require_dir(TOWN_CENTRE / "frames", "Town Centre frames").glob("*.jpg"))[:IMAGES]
    street_jpeg = (models / "test_towncentre_street.jpg").read_bytes()
    phases = Phases()
    stack: Stack | None = None
    try:
        with phases("base images (found, pulled or stand-ins)"):
            postgres_image = ensure_base_images()
        with phases("posemetry image (--build-context models=...)"):
            build_image(models)
            run(["docker", "run", "--rm", "posemetry:latest", "bench", "--help"])
        stack = Stack(PROJECT, postgres_image, free_port())
        stack.down()  # leftovers of an interrupted run
        with phases("compose up until /readyz"):
            stack.compose("up", "-d")
            wait_until(lambda: _ready(stack), "the API ready (database and Redis reachable)")
        with phases("migrations and an admin key"):
            key = _migrated_with_an_admin_key(stack)
        with phases(f"{FRAMES} keypoint frames until calibrated and measured"):
            posted = _keypoint_frames_calibrate_and_are_measured(stack, key)
        with phases("one image frame through pose"):
            _an_image_frame_is_posed(stack, key, street_jpeg)
        with phases("--scale worker-pose=3, one killed mid-job"):
            images = _a_pose_worker_killed_mid_job_loses_nothing(stack, key, town_frames, phases)
        with phases("database stopped: 503, then started"):
            posted += _posts_while_the_database_is_down_are_refused_then_accepted(stack, key)
        with phases("database restarted under a stream of posts"):
            posted += _a_database_restart_under_load_loses_nothing(stack, key, phases)
        with phases("every frame measured, rows counted"):
            _every_frame_is_stored_once_and_measured(stack, posted, images)
    except BaseException:
        if stack is not None:
            print(stack.logs())
        raise
    finally:
        if stack is not None:
            with phases("compose down -v"):
                stack.down()
        with capsys.disabled():
            print("\n" + phases.table())


def _ready(stack: Stack) -> bool:
    try:
        return stack.http("GET", "/readyz").status == 200
    except OSError:
        return False


def _migrated_with_an_admin_key(stack: Stack) -> str:
    migrate = [c for c in stack.containers() if c["Service"] == "migrate"]
    assert [c["ExitCode"] for c in migrate] == [0], migrate
    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    assert stack.psql("SELECT version_num FROM alembic_version") == head
    # As README says: an admin key created on the database by the image's own command, printed alone on stdout.
    out = stack.compose("run", "--rm", "--no-deps", "-T", "migrate", "keys", "create", "--admin", "--name", "ops")
    key = out.strip().splitlines()[-1]
    assert key.startswith("pm_"), out
    assert stack.http("GET", "/v1/cameras").status == 401
    assert stack.http("GET", "/v1/cameras", key=key).status == 200
    return key


def _frame(frame_id: str, k: int, people: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "timestamp": (START + timedelta(seconds=FRAME_SPACING_S * k)).isoformat(),
        "frame_id": frame_id,
        "people": people,
    }


class Street:
    """A simulated surveillance camera's people (bench.simulate), PEOPLE per frame, with their true positions."""

    scene = draw_scene(SceneConfig.surveillance(n_people=FRAMES * PEOPLE), np.random.default_rng(7))

    @classmethod
    def people(cls, k: int) -> list[dict[str, Any]]:
        rows = slice((k % FRAMES) * PEOPLE, (k % FRAMES + 1) * PEOPLE)
        tops, bottoms = cls.scene.tops_px[rows], cls.scene.bottoms_px[rows]
        return [{"keypoints": coco_person(tuple(t), tuple(b))} for t, b in zip(tops, bottoms, strict=True)]

    @classmethod
    def truth_m(cls, k: int, i: int, j: int) -> float:
        points = cls.scene.points_bottom[k * PEOPLE : (k + 1) * PEOPLE]
        return float(np.linalg.norm(points[i] - points[j]))


def _keypoint_frames_calibrate_and_are_measured(stack: Stack, key: str) -> int:
    width, height = Street.scene.image_size
    camera = {"image_width_px": width, "image_height_px": height, "person_height_m": 1.7}
    assert stack.http("PUT", "/v1/cameras/street", camera, key=key).status == 201
    urls = []
    for k in range(FRAMES):
        answer = stack.http("POST", "/v1/cameras/street/keypoints", _frame(f"s-{k}", k, Street.people(k)), key=key)
        assert answer.status == 202, answer
        urls.append(answer.body["url"])
    wait_until(lambda: all(stack.http("GET", u, key=key).body["status"] == "done" for u in urls), "frames measured")
    calibration = stack.http("GET", "/v1/cameras/street/calibration", key=key).body
    assert calibration["status"] == "calibrated", calibration
    errors = []
    for k, url in enumerate(urls):
        result = stack.http("GET", url, key=key).body["result"]
        assert len(result["people"]) == PEOPLE
        errors += [abs(p["distance_m"] / Street.truth_m(k, p["i"], p["j"]) - 1) for p in result["pairs"]]
    # Distances near the truth (tests/e2e holds the accuracy to account; this is the same service in containers).
    assert np.median(errors) < 0.1, np.median(errors)
    return FRAMES


def _image_camera(stack: Stack, key: str) -> None:
    camera = {"image_width_px": 1920, "image_height_px": 1080}
    assert stack.http("PUT", "/v1/cameras/town", camera, key=key).status in (200, 201)


def _post_image(stack: Stack, key: str, frame_id: str, jpeg: bytes) -> str:
    path = f"/v1/cameras/town/frames?frame_id={frame_id}&timestamp=2026-03-01T09:00:00Z"
    answer = stack.http("POST", path, jpeg, key=key)
    assert answer.status == 202 and answer.body["status"] == "detecting", answer
    return str(answer.body["url"])


def _posed(stack: Stack, key: str, url: str) -> bool:
    frame = stack.http("GET", url, key=key).body
    return bool(frame["status"] != "detecting")


def _an_image_frame_is_posed(stack: Stack, key: str, jpeg: bytes) -> None:
    _image_camera(stack, key)
    url = _post_image(stack, key, "street-photo", jpeg)
    wait_until(lambda: _posed(stack, key, url), "pose on the image frame")
    frame = stack.http("GET", url, key=key).body
    # About 17 pedestrians in this frame; the camera has no calibration yet, so its people wait, found.
    assert frame["status"] == "pending" and frame["people"] >= 8 and frame["pose_model"], frame


def _a_pose_worker_killed_mid_job_loses_nothing(stack: Stack, key: str, jpegs: list[Path], phases: Phases) -> int:
    stack.compose("up", "-d", "--no-recreate", "--scale", "worker-pose=3")
    wait_until(lambda: stack.redis("SCARD", "rq:workers:pose") == "3", "three pose workers")
    urls: list[str] = []
    killed: tuple[str, str] | None = None
    tried: list[str] = []
    for attempt in range(5):  # a job may end between being seen and the kill: then another batch and worker are tried
        post = functools.partial(_post_images, stack, key, jpegs, f"town-{attempt}")
        container, job, posted = _kill_a_busy_pose_worker(stack, tried, post)
        urls += posted
        tried.append(container)
        # Killed in the middle of the job: its frame is still waiting for pose (the job's last act would end that).
        frame_url = f"/v1/cameras/town/frames/{job.removeprefix('pose-')}"
        if stack.http("GET", frame_url, key=key).body["status"] == "detecting":
            killed = (container, job)
            break
    assert killed is not None, "no pose worker was caught mid-job"
    phases.note(f"killed pose worker {killed[0]} in the middle of job {killed[1]} (attempt {len(tried)})")
    # Docker leaves a killed container stopped (an operator's act, unlike a crash); `up` starts it again.
    stack.compose("up", "-d", "--no-recreate", "--scale", "worker-pose=3")
    wait_until(lambda: all(_posed(stack, key, url) for url in urls), "every image posed, the killed job's too")
    for url in urls:
        frame = stack.http("GET", url, key=key).body
        # Pending, or already measured: with ~180 people found the camera calibrates from the footage.
        assert frame["status"] in ("pending", "done") and frame["people"] > 0, frame
    # The killed job's frame is among them: it ran again, elsewhere or in the restarted container.
    assert killed[1].removeprefix("pose-") in {url.rsplit("/", 1)[1] for url in urls}
    return 1 + len(urls)


def _post_images(stack: Stack, key: str, jpegs: list[Path], prefix: str) -> list[str]:
    return [_post_image(stack, key, f"{prefix}-{k}", path.read_bytes()) for k, path in enumerate(jpegs)]


def _kill_a_busy_pose_worker(
    stack: Stack, skipped: list[str], post: Callable[[], list[str]]
) -> tuple[str, str, list[str]]:
    """Kill a pose worker caught with a job in hand; its container, its job and the URLs `post` returned.

    The watcher is in place before `post` gives the workers their batch (three workers pose nine frames before a
    `docker compose exec` started after the posts has looked: CI saw exactly that), and the kill follows the
    moment it names a worker, while the batch is still being posted (a job lasts a few hundred milliseconds)."""
    find = ["exec", "-T", "api", "python", "-c", FIND_BUSY_POSE_WORKER, *skipped]
    watcher = stack.start(*find)
    assert watcher.stdout is not None and watcher.stderr is not None
    with ThreadPoolExecutor(1) as poster:
        try:
            ready, _, _ = select.select([watcher.stdout], [], [], DEADLINE_S)
            first = watcher.stdout.readline().strip() if ready else ""
            if first != "watching":
                watcher.kill()
                raise AssertionError(f"the watcher did not start ({first!r}): {watcher.stderr.read()[-2000:]}")
            posting = poster.submit(post)
            # The same buffered stream as the first line, to the watcher's end (it gives up on its own after 60 s).
            out = watcher.stdout.read()
            err = watcher.stderr.read()
            watcher.wait(timeout=DEADLINE_S)
        finally:
            if watcher.poll() is None:
                watcher.kill()
                watcher.wait()
        assert watcher.returncode == 0, f"{' '.join(find[:5])} exited with {watcher.returncode}: {out}{err}"
        container, job = out.split()
        run(["docker", "kill", container])
        return container, job, posting.result()


def _post_until_accepted(stack: Stack, key: str, body: dict[str, Any], refusals: list[Answer]) -> Answer:
    """A well-behaved client: on 503, wait as Retry-After says and send the same frame again."""
    deadline = time.monotonic() + DEADLINE_S
    while True:
        answer = stack.http("POST", "/v1/cameras/street/keypoints", body, key=key)
        if answer.status != 503:
            return answer
        refusals.append(answer)
        assert time.monotonic() < deadline, "the database did not come back"
        time.sleep(min(float(answer.headers["retry-after"]), 2.0))


def _is_database_unavailable(answer: Answer) -> bool:
    return (
        answer.status == 503
        and answer.headers.get("content-type", "").startswith("application/problem+json")
        and str(answer.body["type"]).endswith("/database-unavailable")
        and float(answer.headers.get("retry-after", "0")) > 0
    )


def _posts_while_the_database_is_down_are_refused_then_accepted(stack: Stack, key: str) -> int:
    stack.compose("stop", "postgres")
    bodies = [_frame(f"down-{k}", FRAMES + k, Street.people(k)) for k in range(3)]
    for body in bodies:
        answer = stack.http("POST", "/v1/cameras/street/keypoints", body, key=key)
        assert _is_database_unavailable(answer), answer
    assert stack.http("GET", "/readyz").status == 503
    stack.compose("start", "postgres")
    refusals: list[Answer] = []
    for body in bodies:
        assert _post_until_accepted(stack, key, body, refusals).status == 202
    assert all(_is_database_unavailable(answer) for answer in refusals), refusals
    return len(bodies)


def _a_database_restart_under_load_loses_nothing(stack: Stack, key: str, phases: Phases) -> int:
    accepted: list[Answer] = []
    refusals: list[Answer] = []
    failures: list[BaseException] = []
    restarted = threading.Event()

    def camera_system() -> None:
        after_restart = 0
        try:
            for k in range(200):
                body = _frame(f"restart-{k}", 100 + k, Street.people(k))
                accepted.append(_post_until_accepted(stack, key, body, refusals))
                after_restart += restarted.is_set()
                if after_restart == 5:
                    return
        except BaseException as exc:  # re-raised by the test's thread
            failures.append(exc)

    poster = threading.Thread(target=camera_system)
    poster.start()
    try:
        wait_until(lambda: len(accepted) >= 3 or bool(failures), "posts before the restart", every_s=0.05)
        stack.compose("restart", "postgres")
    finally:
        restarted.set()
        poster.join(DEADLINE_S)
    if failures:
        raise failures[0]
    assert not poster.is_alive()
    assert [a.status for a in accepted] == [202] * len(accepted), [a.status for a in accepted if a.status != 202]
    # Posts that met the restart were refused as a database outage (never a 500), then accepted on retry.
    assert all(_is_database_unavailable(answer) for answer in refusals), refusals
    phases.note(f"database restart under load: {len(accepted)} frames accepted after {len(refusals)} refusals (503)")
    return len(accepted)


def _every_frame_is_stored_once_and_measured(stack: Stack, posted: int, images: int) -> None:
    unfinished = "SELECT count(*) FROM frames WHERE camera_id = 'street' AND status <> 'done'"
    wait_until(lambda: stack.psql(unfinished) == "0", "every keypoint frame measured after the faults")
    assert stack.psql("SELECT count(*) FROM frames WHERE camera_id = 'street'") == str(posted)
    stored_people = "SELECT count(*) FROM observations WHERE camera_id = 'street'"
    assert stack.psql(stored_people) == str(posted * PEOPLE)
    assert stack.psql("SELECT count(*) FROM frames WHERE camera_id = 'town'") == str(images)
    assert stack.psql("SELECT count(*) FROM frames WHERE camera_id = 'town' AND status = 'detecting'") == "0"
    # The stack is whole again: the API answers, every service but the one-shot migration runs, and none had to be
    # restarted by Docker (no process died of the outages).
    assert _ready(stack)
    containers = [c for c in stack.containers() if c["Service"] != "migrate"]
    assert all(c["State"] == "running" for c in containers), containers
    restarts = run(["docker", "inspect", "-f", "{{.Name}} {{.RestartCount}}", *(c["ID"] for c in containers)])
    assert all(line.endswith(" 0") for line in restarts.splitlines()), restarts
