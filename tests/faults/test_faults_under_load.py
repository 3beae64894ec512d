"""Faults as they happen in production: several clients posting all through each one, then the rows counted in SQL.

The Compose deployment (`posemetry api`, two supervised `posemetry worker` processes, a standalone redis-server and
PostgreSQL), with concurrent clients posting frames to several cameras (tests/faults/fleet.py) while

- PostgreSQL is down for seconds: every post meets the outage (503, never 500) and is posted again until accepted;
- a worker is killed in the middle of a webhook delivery (the receiver holding the request): the delivery is made
  again, with the same `webhook-id`, and nothing else is sent twice;
- Redis is killed and comes back empty while webhook deliveries are pending and their receiver is down: every
  event is delivered once the receiver is back, with its id, none twice. (Last: the workers' registrations go with
  the old Redis, and the test above finds the worker to kill by its registration.)

After each, SQL says: every accepted frame stored once with its people, evidence counted once, violation events
as the results list them, every frame measured. Each test prints its recovery times (README, "When something
fails"). Retries and leases are shortened by settings so the recoveries take seconds, not the defaults' minutes.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import Counter
from collections.abc import Iterator
from typing import Any

import pytest
import redis
from sqlalchemy import create_engine, text

from tests.faults.fleet import FLEET_FRAMES, Fleet, assert_nothing_lost_or_doubled, posting, sql_counts
from tests.faults.harness import (
    Client,
    SimulatedCamera,
    Stack,
    compose_stack,
    kill_worker_running,
    post_frames,
    wait_until,
)
from tests.support.receiver import Answer, Receiver

CLIENTS = 6
RECOVERY_DEADLINE_S = 90.0
ALARM = {"distance_threshold": {"value": 1000, "unit": "m"}}  # every pair a violation: every frame an event


@pytest.fixture(scope="module")
def stack() -> Iterator[Stack]:
    with compose_stack(
        calibration_sample_cap="2000",
        webhook_allowed_networks="127.0.0.0/8",
        webhook_cooldown_s="0",
        webhook_retry_base_s="0.5",
        webhook_retry_cap_s="2",
        webhook_max_attempts="100",
        # Long enough that a loaded machine does not time out an attempt the receiver answered: that attempt would
        # rightly be made again (deliveries are at least once), and the Redis test counts every event exactly once.
        webhook_timeout_s="3",
        webhook_lease_margin_s="2",
    ) as started:
        yield started


def calibrated(client: Client, camera_id: str, seed: int, **settings: Any) -> SimulatedCamera:
    """A camera calibrated by a forced solve on five frames, ready to measure what comes next."""
    camera = SimulatedCamera.draw(camera_id, frames=FLEET_FRAMES, people_per_frame=6, seed=seed)
    answer = client.request("PUT", f"/v1/cameras/{camera_id}", {**camera.settings(), **settings})
    assert answer.status == 201, answer
    urls = post_frames(client, camera, 5)
    assert client.request("POST", f"/v1/cameras/{camera_id}/calibration").status == 202
    wait_until(lambda: all(client.get(url)["status"] == "done" for url in urls), f"{camera_id} calibrated")
    return camera


def all_measured(stack: Stack, camera_ids: list[str]) -> bool:
    return all(set(sql_counts(stack.database_url, c).statuses) == {"done"} for c in camera_ids)


def subscribe(client: Client, receiver: Receiver, camera_id: str) -> tuple[str, str]:
    answer = client.request(
        "POST",
        "/v1/webhooks",
        {"url": receiver.url, "camera_ids": [camera_id], "event_types": ["violation.detected"]},
    )
    assert answer.status == 201, answer
    return answer.body["id"], answer.body["secret"]


def deliveries(stack: Stack, subscription_id: str) -> list[tuple[str, str, int]]:
    """(event id, status, attempts) of a subscription's deliveries."""
    engine = create_engine(stack.database_url.replace("postgresql://", "postgresql+psycopg://", 1))
    try:
        with engine.connect() as db:
            rows = db.execute(
                text("SELECT event_id, status, attempts FROM webhook_deliveries WHERE subscription_id = :s"),
                {"s": uuid.UUID(subscription_id)},
            ).all()
    finally:
        engine.dispose()
    return [(str(event_id), status, int(attempts)) for event_id, status, attempts in rows]


def test_posts_all_through_a_database_outage_are_503_then_stored_once(stack: Stack) -> None:
    client = stack.client
    cameras = [calibrated(client, "lot", seed=21), calibrated(client, "dock", seed=22)]
    pids = [worker.process.pid for worker in stack.workers]
    with posting(Fleet(client, cameras, CLIENTS)) as fleet:
        time.sleep(1.0)
        stack.cluster.stop_server()
        stopped_at = time.monotonic()
        try:
            time.sleep(0.5)
            ready = client.request("GET", "/readyz")
            assert ready.status == 503 and ready.body["checks"]["database"].startswith("unreachable")
            time.sleep(2.5)
        finally:
            stack.cluster.start_server()
        started_at = time.monotonic()
        time.sleep(1.5)
    last_post = time.monotonic()
    print(f"\ndatabase down for {started_at - stopped_at:.1f} s: {fleet.summary()}")
    statuses = fleet.statuses()
    assert set(statuses) <= {200, 202, 503}, statuses  # never a 500
    assert set(fleet.problems()) == {"database-unavailable"} and statuses[503] >= CLIENTS
    first, last = fleet.refused_between() or (0.0, 0.0)
    assert first < stopped_at + 1.0 and last > started_at - 1.0, "the clients did not post all through the outage"
    accepted_again = fleet.first_accepted_after(started_at)
    wait_until(lambda: all_measured(stack, ["lot", "dock"]), "every frame measured", timeout_s=RECOVERY_DEADLINE_S)
    measured = time.monotonic() - last_post
    for camera in cameras:
        assert_nothing_lost_or_doubled(fleet, sql_counts(stack.database_url, camera.camera_id), camera.camera_id)
    assert [worker.process.pid for worker in stack.workers] == pids  # the workers rode it out
    print(
        f"recovery: frames accepted again {accepted_again:.1f} s after PostgreSQL came back; every frame measured "
        f"{measured:.1f} s after the last post"
    )


def test_a_worker_killed_mid_delivery_sends_it_again_with_the_same_id_and_nothing_else_twice(stack: Stack) -> None:
    client = stack.client
    receiver = Receiver().start()
    try:
        subscription_id, secret = subscribe(client, receiver, "bell")
        bell = calibrated(client, "bell", seed=41, **ALARM)
        wait_until(
            lambda: {status for _, status, _ in deliveries(stack, subscription_id)} == {"delivered"},
            "the calibration frames' events delivered",
        )
        lane = calibrated(client, "lane", seed=42)
        with posting(Fleet(client, [lane], CLIENTS)) as fleet:
            receiver.answers.append(Answer(delay_s=10.0))  # the next request is held while its worker is killed
            before = len(receiver.received())
            post_frames(client, bell, 1)
            wait_until(lambda: len(receiver.received()) > before, "the held delivery", poll_s=0.005)
            _, pid, killed_at = kill_worker_running(stack.queue_redis, "webhooks")
            time.sleep(1.0)
        wait_until(
            lambda: (
                len(receiver.received()) > before + 1
                and {status for _, status, _ in deliveries(stack, subscription_id)} == {"delivered"}
            ),
            "the interrupted delivery made again",
            timeout_s=RECOVERY_DEADLINE_S,
        )
        recovered_s = time.monotonic() - killed_at
    finally:
        receiver.stop()
    print(f"\nworker {pid} killed mid-delivery: {fleet.summary()}")
    received = receiver.received()
    ids = Counter(request.webhook_id for request in received)
    events = {event_id for event_id, _, _ in deliveries(stack, subscription_id)}
    held = received[before].webhook_id
    assert set(ids) == events and ids[held] == 2, ids  # at least once: the same id again
    assert all(n == 1 for event_id, n in ids.items() if event_id != held), "an event not interrupted came twice"
    assert received[before].body == received[-1].body and received[-1].webhook_id == held
    for request in received:
        request.verify(secret)
    assert set(fleet.statuses()) <= {200, 202}, fleet.statuses()
    wait_until(lambda: all_measured(stack, ["lane"]), "every frame measured", timeout_s=RECOVERY_DEADLINE_S)
    assert_nothing_lost_or_doubled(fleet, sql_counts(stack.database_url, "lane"), "lane")
    print(f"recovery: the interrupted delivery delivered {recovered_s:.1f} s after the kill, with the same webhook-id")


def _redis_answers(connection: redis.Redis) -> bool:
    try:
        return bool(connection.ping())
    except (redis.ConnectionError, redis.TimeoutError, OSError):
        return False


def test_redis_restarted_empty_with_deliveries_pending_and_the_receiver_down_delivers_every_event_once(
    stack: Stack,
) -> None:
    client = stack.client
    receiver = Receiver().start()
    receiver.stop()  # its port refuses connections until it starts again
    subscription_id, secret = subscribe(client, receiver, "alarm")
    cameras = [calibrated(client, "alarm", seed=31, **ALARM), calibrated(client, "gate", seed=32)]
    try:
        with posting(Fleet(client, cameras, CLIENTS)) as fleet:
            wait_until(
                lambda: sum(attempts > 0 for _, _, attempts in deliveries(stack, subscription_id)) >= 5,
                "deliveries failing against the receiver that is down",
            )
            stack.redis.kill()
            killed_at = time.monotonic()
            threading.Timer(1.5, stack.redis.start).start()  # Compose restarts it: empty, on the same socket
            wait_until(lambda: _redis_answers(stack.queue_redis), "Redis back", poll_s=0.01)
            redis_back = time.monotonic()
            time.sleep(1.5)
        pending = deliveries(stack, subscription_id)
        assert pending and {status for _, status, _ in pending} == {"pending"}, pending
        receiver.start()
        receiver_up = time.monotonic()
        wait_until(
            lambda: all_measured(stack, ["alarm", "gate"]), "every frame measured", timeout_s=RECOVERY_DEADLINE_S
        )
        wait_until(
            lambda: {status for _, status, _ in deliveries(stack, subscription_id)} == {"delivered"},
            "every event delivered",
            timeout_s=RECOVERY_DEADLINE_S,
        )
        delivered_s = time.monotonic() - receiver_up
    finally:
        receiver.stop()
    print(f"\nRedis killed, back empty {redis_back - killed_at:.1f} s later, receiver down: {fleet.summary()}")
    statuses = fleet.statuses()
    assert set(statuses) <= {200, 202, 503}, statuses
    assert set(fleet.problems()) <= {"queue-unavailable"}
    accepted_again = fleet.first_accepted_after(redis_back)

    events = {event_id for event_id, _, _ in deliveries(stack, subscription_id)}
    received = Counter(request.webhook_id for request in receiver.received())
    assert set(received) == events, "an event was not delivered, or one was made up"
    assert set(received.values()) == {1}, "an event was delivered twice"
    frames = {request.verify(secret)["data"]["frame"]["client_frame_id"] for request in receiver.received()}
    counts = sql_counts(stack.database_url, "alarm")
    assert len(frames) == len(events) == counts.statuses["done"]  # one event per measured frame, each its own
    for camera in cameras:
        assert_nothing_lost_or_doubled(fleet, sql_counts(stack.database_url, camera.camera_id), camera.camera_id)
    print(
        f"recovery: frames accepted {accepted_again:.1f} s after Redis was back; {len(events)} events delivered, "
        f"each once, the last {delivered_s:.1f} s after the receiver came back"
    )
