"""Faults in the Compose deployment: `posemetry api` and two `posemetry worker` processes on a standalone
redis-server and a PostgreSQL server, each of them started and stopped here as Compose would.

- A worker killed with SIGKILL in the middle of a solve, and not restarted: the other worker retries the job.
- Redis killed while frames stream in, and started again empty (no persistence, the hardest case): nothing
  accepted is lost, a frame refused with 503 and posted again is stored once.
- PostgreSQL stopped while a solve runs, then started again: the API answers 503 problems meanwhile (never 500),
  the workers stay up, and the interrupted work is done once the database is back, with no restart and no new
  input.

Workers are supervised as Compose's `restart: unless-stopped` would (a worker may exit when Redis goes away
under it); the API is not: it must ride out both outages.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from tests.faults.harness import (
    Answer,
    Client,
    SimulatedCamera,
    Stack,
    compose_stack,
    create_camera,
    kill_worker_running,
    post_frames,
    post_until_accepted,
    started_job,
    wait_until,
)

RECOVERY_DEADLINE_S = 60.0
REDIS_DOWN_S = 1.5


@pytest.fixture(scope="module")
def stack() -> Iterator[Stack]:
    with compose_stack(calibration_sample_cap="20000") as started:
        yield started


def big_camera(client: Client, camera_id: str) -> tuple[SimulatedCamera, list[str]]:
    """120 frames of 100 people, waiting for a solve that takes seconds (12000 people); the scene has people for one
    frame more, which a test may post later."""
    camera = SimulatedCamera.draw(camera_id, frames=121, people_per_frame=100, seed=11)
    create_camera(client, camera)
    return camera, post_frames(client, camera, 120)


def all_done(client: Client, urls: list[str]) -> bool:
    return all(client.get(url)["status"] == "done" for url in urls)


def test_a_killed_workers_solve_is_finished_by_the_other_worker(stack: Stack) -> None:
    client = stack.client
    big_camera(client, "yard")
    for worker in stack.workers:
        worker.pause()  # nobody restarts the killed worker: the survivor must take its job over
    try:
        assert client.request("POST", "/v1/cameras/yard/calibration").status == 202
        _, pid, killed_at = kill_worker_running(stack.queue_redis, "calibration")
        history = wait_until(
            lambda: client.get("/v1/cameras/yard/calibration/history")["items"],
            "the other worker to retry the killed solve",
            timeout_s=RECOVERY_DEADLINE_S,
        )
        print(f"\nkilled solve (worker {pid}): retried by the other worker {time.monotonic() - killed_at:.1f} s later")
        assert sum(worker.process.poll() is None for worker in stack.workers) == 1  # no restart happened
    finally:
        for worker in stack.workers:
            worker.resume()
    (version,) = history
    assert version["status"] == "ok" and version["is_current"]


def test_redis_restarted_empty_while_frames_stream_in_loses_nothing(stack: Stack) -> None:
    client = stack.client
    camera = SimulatedCamera.draw("gate", frames=60, people_per_frame=10, seed=7)
    create_camera(client, camera)
    urls = post_frames(client, camera, 5)
    assert client.request("POST", "/v1/cameras/gate/calibration").status == 202
    wait_until(lambda: all_done(client, urls), "the first frames measured")

    refusals: list[Answer] = []
    answers = []
    for k in range(55):
        if k == 20:
            stack.redis.kill()
            killed_at = time.monotonic()
            # Compose restarts the container a moment later: an empty Redis on the old socket path.
            threading.Timer(REDIS_DOWN_S, stack.redis.start).start()
        answers.append(post_until_accepted(client, camera, refusals))
        if k == 20:
            print(f"\nRedis killed: frames accepted again {time.monotonic() - killed_at:.1f} s later")
    assert refusals and all(r.is_problem and r.body["type"].endswith("/queue-unavailable") for r in refusals)
    # Each refused frame had been stored: its retry is answered 200 with the same frame, not stored twice.
    assert {r.body["frame_id"] for r in refusals} <= {a.body["frame_id"] for a in answers if a.status == 200}
    urls += [answer.body["url"] for answer in answers]
    assert len(set(urls)) == 60
    recovered_at = time.monotonic()
    wait_until(lambda: all_done(client, urls), "every accepted frame measured", timeout_s=RECOVERY_DEADLINE_S)
    print(f"every frame measured {time.monotonic() - recovered_at:.1f} s after the last post")
    assert stack.api.poll() is None and client.ready()


def test_postgres_outage_is_503_then_the_interrupted_work_completes_without_restart(stack: Stack) -> None:
    client = stack.client
    camera, urls = big_camera(client, "lot")
    pids = [worker.process.pid for worker in stack.workers]
    assert client.request("POST", "/v1/cameras/lot/calibration").status == 202
    wait_until(lambda: started_job(stack.queue_redis, "calibration"), "the solve to start", poll_s=0.005)
    stack.cluster.stop_server()
    stopped_at = time.monotonic()
    try:
        ready = client.request("GET", "/readyz")
        assert ready.status == 503 and ready.is_problem and ready.body["checks"]["database"].startswith("unreachable")
        body = camera.next_frame()
        refused = client.request("POST", "/v1/cameras/lot/keypoints", body)
        assert refused.status == 503 and refused.is_problem, refused
        assert refused.body["type"].endswith("/database-unavailable") and refused.headers.get("retry-after")
        for path in ("/v1/cameras/lot", urls[0], "/v1/cameras/lot/calibration/history", "/v1/cameras"):
            answer = client.request("GET", path)
            assert answer.status == 503 and answer.is_problem, (path, answer)
        scrape = client.request("GET", "/metrics")  # scrapes go on, and say the database is out of reach
        assert scrape.status == 200 and 'posemetry_metrics_source_up{source="database"} 0.0' in scrape.body
        # The solve fails (and its retries); the workers stay up.
        wait_until(lambda: not started_job(stack.queue_redis, "calibration"), "the solve to fail")
        time.sleep(1.0)
        assert [worker.process.poll() for worker in stack.workers] == [None, None]
    finally:
        stack.cluster.start_server()
    print(f"\nPostgreSQL down for {time.monotonic() - stopped_at:.1f} s")
    started_at = time.monotonic()
    # Nothing new is posted: the workers' recovery pass finds the forced solve still outstanding.
    history = wait_until(
        lambda: client.request("GET", "/v1/cameras/lot/calibration/history").body.get("items"),
        "the interrupted solve to be done again",
        timeout_s=RECOVERY_DEADLINE_S,
    )
    wait_until(lambda: all_done(client, urls), "the waiting frames measured", timeout_s=RECOVERY_DEADLINE_S)
    print(f"solve and 120 frames done {time.monotonic() - started_at:.1f} s after PostgreSQL came back")
    assert len(history) == 1 and history[0]["is_current"]
    accepted = client.request("POST", "/v1/cameras/lot/keypoints", body)  # the client's retry of the refused frame
    assert accepted.status == 202, accepted
    wait_until(lambda: client.get(accepted.body["url"])["status"] == "done", "the retried frame measured")
    assert [worker.process.pid for worker in stack.workers] == pids  # survived: no restart
    assert client.ready()
