"""Webhooks through the real thing: the API, real Redis, real RQ workers (in this process, and a `posemetry worker`
subprocess with its scheduler), real SQLite/PostgreSQL, and a real HTTP receiver on loopback that verifies every
signature with the reference `standardwebhooks` library."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import redis
from fastapi.testclient import TestClient
from rq import Queue
from rq.job import Job
from rq.registry import ScheduledJobRegistry
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.app import create_app
from service.cameras.repository import delete_camera
from service.domain import METRES_PER_FOOT
from service.frames.ingest import add_keypoint_frame
from service.frames.keypoints import person_from_centres
from service.frames.repository import get_frame
from service.observability.metrics import WEBHOOK_DELIVERIES, WEBHOOK_OUTCOMES
from service.queue import WEBHOOKS_QUEUE, RedisDispatcher, webhook_job_id
from service.settings import get_settings
from service.store import WebhookAttempt, WebhookDelivery, WebhookSubscription
from service.webhooks import repository as store
from service.webhooks.delivery import RESPONSE_LOG_BYTES
from service.webhooks.events import first_attempts
from tests.support.app import ADMIN_KEY, bearer
from tests.support.jobs import IMAGE_SIZE, Camera, run_jobs, simulated_camera, store_frames
from tests.support.receiver import Answer, Received, Receiver
from workers.main import requeue_deliveries, requeue_pending
from workers.webhooks import deliver_webhook

REPO = Path(__file__).resolve().parents[2]
T0 = datetime(2026, 1, 1, 12, tzinfo=UTC)
COOLDOWN_S = 60


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request: pytest.FixtureRequest) -> str:
    """Deliveries are claimed and recorded by conditional updates: both databases must agree."""
    return str(request.param)


@pytest.fixture
def hooks(environment: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Webhook settings for these tests: loopback allowed (the receiver), short timeouts."""
    extra = {
        "POSEMETRY_WEBHOOK_ALLOWED_NETWORKS": "127.0.0.0/8",
        "POSEMETRY_WEBHOOK_TIMEOUT_S": "2",
        "POSEMETRY_WEBHOOK_COOLDOWN_S": str(COOLDOWN_S),
    }
    for name, value in extra.items():
        monkeypatch.setenv(name, value)
    get_settings.cache_clear()
    return {**environment, **extra}


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    server = Receiver().start()
    yield server
    server.stop()


@pytest.fixture
def api(hooks: dict[str, str], redis_dispatcher: RedisDispatcher) -> Iterator[TestClient]:
    with TestClient(create_app(get_settings(), dispatcher=redis_dispatcher), headers=bearer(ADMIN_KEY)) as client:
        yield client


def subscribe(api: TestClient, receiver: Receiver, **fields: Any) -> dict[str, Any]:
    """A subscription to the receiver, on a path of its own (so the receiver can tell subscriptions apart)."""
    response = api.post("/v1/webhooks", json={"url": f"{receiver.url}/{uuid.uuid4().hex}", **fields})
    assert response.status_code == 201, response.text
    return response.json()


def requests_for(receiver: Receiver, subscription: dict[str, Any]) -> list[Received]:
    path = subscription["url"].removeprefix(f"http://127.0.0.1:{receiver.port}")
    return [request for request in receiver.received() if request.path == path]


def payloads(receiver: Receiver, subscription: dict[str, Any], event_type: str | None = None) -> list[dict[str, Any]]:
    """The bodies the subscription's receiver got, each verified with its secret, optionally of one type."""
    verified = [request.verify(subscription["secret"]) for request in requests_for(receiver, subscription)]
    return [p for p in verified if event_type is None or p["type"] == event_type]


def post_people(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    camera: Camera,
    people: list[int],
    at: datetime,
    *,
    noise_px: float = 0.0,
    client_frame_id: str | None = None,
    track_ids: list[str | None] | None = None,
) -> uuid.UUID:
    """Post one frame with these people of the simulated scene (indices), as the API stores it."""
    rng = np.random.default_rng(len(people) + int(at.timestamp()))
    tops = camera.scene.tops_px[people] + rng.normal(0, noise_px, (len(people), 2))
    bottoms = camera.scene.bottoms_px[people] + rng.normal(0, noise_px, (len(people), 2))
    ids = track_ids or [None] * len(people)
    persons = [
        person_from_centres(tuple(t), tuple(b), IMAGE_SIZE, track_id=track)
        for t, b, track in zip(tops, bottoms, ids, strict=True)
    ]
    with sessions() as session, session.begin():
        frame, _ = add_keypoint_frame(
            session, camera.camera_id, timestamp=at, people=persons, client_frame_id=client_frame_id
        )
    redis_dispatcher.frames_stored([(camera.camera_id, frame.id)])
    return frame.id


def close_pairs(camera: Camera, far_from: list[int] = (), max_m: float = 1.1, away_m: float = 2.5) -> list[list[int]]:
    """Pairs of scene people standing closer than max_m (truth), each person away_m from every `far_from` one."""
    ground = camera.scene.points_bottom
    distances = np.linalg.norm(ground[:, None, :] - ground[None, :, :], axis=-1)
    away = np.all(distances[:, list(far_from)] > away_m, axis=1) if far_from else np.ones(len(ground), bool)
    return [
        [int(i), int(j)] for i, j in zip(*np.nonzero(distances < max_m), strict=True) if i < j and away[i] and away[j]
    ]


def far_person(camera: Camera, people: list[int], away_m: float = 2.5) -> int:
    """Someone standing more than away_m from each of `people`."""
    ground = camera.scene.points_bottom
    distances = np.linalg.norm(ground[:, None, :] - ground[None, people, :], axis=-1)
    return int(np.flatnonzero(np.all(distances > away_m, axis=1))[0])


def calibrated_camera(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> Camera:
    camera = simulated_camera(sessions, people=400)
    store_frames(sessions, camera, 6, dispatcher=redis_dispatcher)
    run_jobs(connection)
    return camera


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


def _deliveries(sessions: sessionmaker[Session]) -> list[WebhookDelivery]:
    with sessions() as session:
        return list(session.scalars(select(WebhookDelivery).order_by(WebhookDelivery.created_at)))


def _attempts(sessions: sessionmaker[Session], delivery_id: uuid.UUID) -> list[WebhookAttempt]:
    with sessions() as session:
        return list(
            session.scalars(
                select(WebhookAttempt).where(WebhookAttempt.delivery_id == delivery_id).order_by(WebhookAttempt.number)
            )
        )


def _raise_events(sessions: sessionmaker[Session], subscription_id: str, n: int) -> list[uuid.UUID]:
    """n events for one subscription, stored as a worker would (nothing queued yet)."""
    ids = []
    with sessions() as session, session.begin():
        subscription = store.get_subscription(session, uuid.UUID(subscription_id))
        for k in range(n):
            body = f'{{"type":"calibration.updated","timestamp":"2026-01-01T00:00:0{k}Z","data":{{"n":{k}}}}}'
            ids += store.raise_event(
                session, event_type="calibration.updated", camera_id="cam-1", body=body, subscriptions=[subscription]
            )
    return ids


# --------------------------------------------------------------------------------------------------- events


def test_calibration_and_violation_webhooks_end_to_end(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
) -> None:
    calibration = subscribe(api, receiver, event_types=["calibration.updated", "calibration.status_changed"])
    camera = calibrated_camera(sessions, redis_dispatcher, connection)
    status = api.get(f"/v1/cameras/{camera.camera_id}/calibration").json()
    assert status["status"] == "calibrated"
    [updated] = payloads(receiver, calibration, "calibration.updated")
    [changed] = payloads(receiver, calibration, "calibration.status_changed")
    for event in (updated, changed):
        data = event["data"]
        assert data["camera_id"] == camera.camera_id and data["status"] == "calibrated"
        assert data["version"] == status["version"] and data["fx_px"] == pytest.approx(status["fx_px"])
        assert data["normal"] == pytest.approx(status["normal"]) and data["rho_m"] == pytest.approx(status["rho_m"])
        assert (
            data["uncertainty"] == status["uncertainty"] and data["evidence_count"] == status["solved_evidence_count"]
        )
        # Where the principal point, focal length and lens came from, with sigma, and what the solve is worth.
        assert data["camera_model"] == status["camera_model"] and data["quality"] == status["quality"]
        assert data["camera_model"]["principal_point"]["source"] in ("assumed", "estimated")
        assert data["quality"]["grade"] != "unreliable"  # else the violation below would raise no alert
        assert datetime.fromisoformat(event["timestamp"]) <= datetime.now(UTC)
    assert updated["data"]["previous_version"] is None
    assert (changed["data"]["previous_status"], changed["data"]["reason"]) == ("uncalibrated", "calibrated")

    violations = subscribe(api, receiver, event_types=["violation.detected"], camera_ids=[camera.camera_id])
    elsewhere = subscribe(api, receiver, camera_ids=["cam-2"])
    pair = close_pairs(camera)[0]
    loner = far_person(camera, pair)
    frame_id = post_people(
        sessions, redis_dispatcher, camera, [*pair, loner], T0, client_frame_id="f-1", track_ids=["w-1", "w-2", None]
    )
    run_jobs(connection)
    [alert] = payloads(receiver, violations, "violation.detected")
    data = alert["data"]
    with sessions() as session:
        frame = get_frame(session, camera.camera_id, frame_id)
        assert frame is not None and frame.result is not None
        result = frame.result
    [violation] = result["violations"]
    assert data["camera_id"] == camera.camera_id and data["calibration_version"] == status["version"]
    assert data["frame"] == {
        "id": str(frame_id),
        "client_frame_id": "f-1",
        "timestamp": "2026-01-01T12:00:00Z",
        "url": f"/v1/cameras/{camera.camera_id}/frames/{frame_id}",
    }
    [alerted] = data["pairs"]
    assert (alerted["i"], alerted["j"]) == (violation["i"], violation["j"]) == (0, 1)
    assert alerted["distance_m"] == pytest.approx(violation["distance_m"]) and alerted["distance_m"] < 1.8288
    assert alerted["distance_ft"] == pytest.approx(alerted["distance_m"] / METRES_PER_FOOT)
    assert alerted["distance_std_m"] == pytest.approx(violation["distance_std_m"]) and alerted["distance_std_m"] > 0
    assert alerted["distance_std_ft"] == pytest.approx(alerted["distance_std_m"] / METRES_PER_FOOT)
    assert alerted["ground_i_m"] == pytest.approx(result["people"][0]["ground_m"])
    assert alerted["ground_j_m"] == pytest.approx(result["people"][1]["ground_m"])
    # The client's own ids for the two, as posted, in the alert and in the frame's result.
    assert (alerted["track_id_i"], alerted["track_id_j"]) == ("w-1", "w-2")
    assert [person["track_id"] for person in result["people"]] == ["w-1", "w-2", None]
    assert data["distance_threshold_ft"] == pytest.approx(6.0) and data["violation_count"] == 1
    assert data["cooldown_s"] == COOLDOWN_S
    # Calibration subscribers hear no violations, other cameras' subscribers nothing at all.
    assert payloads(receiver, calibration, "violation.detected") == []
    assert api.get(f"/v1/webhooks/{elsewhere['id']}/deliveries").json()["items"] == []

    # The delivery log over the API: one attempt, 200, the receiver's answer.
    [entry] = api.get(f"/v1/webhooks/{violations['id']}/deliveries").json()["items"]
    assert entry["status"] == "delivered" and entry["attempts"] == 1 and entry["last_status_code"] == 200
    [attempt] = api.get(entry["url"]).json()["attempt_log"]
    assert (attempt["outcome"], attempt["status_code"], attempt["response_body"]) == ("delivered", 200, "ok")
    assert attempt["peer"] == f"127.0.0.1:{receiver.port}" and attempt["duration_s"] > 0
    assert requests_for(receiver, violations)[-1].webhook_id == entry["webhook_id"]

    # Manual redelivery: the same event (same webhook-id, same body), signed afresh.
    again = api.post(f"{entry['url']}/redeliver")
    assert again.status_code == 202
    run_jobs(connection)
    first, second = requests_for(receiver, violations)
    assert first.body == second.body and second.verify(violations["secret"]) == alert
    assert api.get(again.json()["url"]).json()["status"] == "delivered"


def test_cooldown_a_lingering_pair_fires_once_per_window_another_pair_at_once(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    camera = calibrated_camera(sessions, redis_dispatcher, connection)
    # No re-solve while the pairs stand there: ground positions stay in one calibration's frame.
    monkeypatch.setenv("POSEMETRY_CALIBRATION_GROWTH_FACTOR", "50")
    get_settings.cache_clear()
    subscription = subscribe(api, receiver, event_types=["violation.detected"])
    lingering = close_pairs(camera)[0]
    other = close_pairs(camera, far_from=lingering)[0]
    # The pair stands still for two and a half minutes, a frame every 10 s with pose noise; the other pair
    # turns up elsewhere in the same camera 20 s in.
    for second in range(0, 150, 10):
        people = lingering + (other if second >= 20 else [])
        post_people(sessions, redis_dispatcher, camera, people, T0 + timedelta(seconds=second), noise_px=1.5)
        run_jobs(connection)
    alerts = payloads(receiver, subscription, "violation.detected")
    fired = [(a["data"]["frame"]["timestamp"], [(p["i"], p["j"]) for p in a["data"]["pairs"]]) for a in alerts]
    assert fired == [
        ("2026-01-01T12:00:00Z", [(0, 1)]),
        ("2026-01-01T12:00:20Z", [(2, 3)]),
        ("2026-01-01T12:01:00Z", [(0, 1)]),
        ("2026-01-01T12:01:20Z", [(2, 3)]),
        ("2026-01-01T12:02:00Z", [(0, 1)]),
        ("2026-01-01T12:02:20Z", [(2, 3)]),
    ]
    assert all(a["data"]["violation_count"] == (2 if a["data"]["frame"]["timestamp"] >= "2026-01-01T12:00:20Z" else 1)
               for a in alerts)  # fmt: skip


# --------------------------------------------------------------------------------------------------- retries


def _delivery_counts() -> Counter[str]:
    """This process's posemetry_webhook_deliveries_total by outcome."""
    return Counter(
        {outcome: int(WEBHOOK_DELIVERIES.labels(outcome=outcome)._value.get()) for outcome in WEBHOOK_OUTCOMES}
    )


def test_a_failed_attempt_is_scheduled_with_backoff_and_logged_truncated(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("POSEMETRY_WEBHOOK_RETRY_BASE_S", "20")
    monkeypatch.setenv("POSEMETRY_WEBHOOK_RETRY_CAP_S", "100")
    monkeypatch.setenv("POSEMETRY_WEBHOOK_MAX_ATTEMPTS", "5")
    get_settings.cache_clear()
    subscription = subscribe(api, receiver)
    [delivery_id] = _raise_events(sessions, subscription["id"], 1)
    receiver.default = Answer(503, b"x" * (3 * RESPONSE_LOG_BYTES))
    registry = ScheduledJobRegistry(WEBHOOKS_QUEUE, connection=connection)
    counted = _delivery_counts()
    waits = []
    for attempt in range(1, 6):
        started = time.time()
        assert deliver_webhook(str(delivery_id), attempt) == ("retry" if attempt < 5 else "failed")
        if attempt < 5:
            next_job = webhook_job_id(delivery_id, attempt + 1)
            assert registry.get_job_ids() == [next_job]
            waits.append(registry.get_scheduled_time(next_job).timestamp() - started)
            Job.fetch(next_job, connection=connection).delete()  # run it here instead, now
    # Waits double from the base, jittered down by at most a quarter, capped (whole seconds: RQ's resolution).
    for wait, nominal in zip(waits, [20, 40, 80, 100], strict=True):
        assert 0.75 * nominal - 1.5 <= wait <= nominal + 0.5, waits
    [entry] = api.get(f"/v1/webhooks/{subscription['id']}/deliveries").json()["items"]
    assert entry["status"] == "failed" and entry["attempts"] == 5 and entry["next_attempt_at"] is None
    assert "gave up after 5 attempts" in entry["last_error"]
    log = api.get(entry["url"]).json()["attempt_log"]
    assert [(a["number"], a["outcome"], a["status_code"]) for a in log] == [
        (1, "retry", 503), (2, "retry", 503), (3, "retry", 503), (4, "retry", 503), (5, "failed", 503),
    ]  # fmt: skip
    assert all(a["response_truncated"] and len(a["response_body"]) == RESPONSE_LOG_BYTES for a in log)
    assert _delivery_counts() - counted == Counter(retrying=4, failed=1)  # posemetry_webhook_deliveries_total
    # Every attempt carried the same webhook-id, and a fresh signature each time.
    requests = receiver.received()
    assert {r.webhook_id for r in requests} == {entry["webhook_id"]} and len(requests) == 5
    for request in requests:
        request.verify(subscription["secret"])
    # A second copy of a job for an attempt already made sends nothing.
    assert deliver_webhook(str(delivery_id), 5) == "skipped"
    assert len(receiver.received()) == 5


def test_retries_on_500_and_connection_refused_then_success_with_a_worker_process(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    api: TestClient,
    receiver: Receiver,
    hooks: dict[str, str],
) -> None:
    """The fault test of issue 5, with the delays scaled down: the receiver fails, then is down (connections
    refused), then comes back; a `posemetry worker -q webhooks` process (which runs RQ's scheduler) delivers
    everything, each event under one webhook-id however often it was tried."""
    subscription = subscribe(api, receiver)
    receiver.default = Answer(500, b"not now")
    env = {
        **os.environ,
        "POSEMETRY_WEBHOOK_RETRY_BASE_S": "0.5",
        "POSEMETRY_WEBHOOK_RETRY_CAP_S": "2",
        "POSEMETRY_WEBHOOK_MAX_ATTEMPTS": "50",
    }
    worker = subprocess.Popen([sys.executable, "-m", "service.cli", "worker", "-q", "webhooks"], cwd=REPO, env=env)
    try:
        events = _raise_events(sessions, subscription["id"], 5)
        redis_dispatcher.deliveries_due(first_attempts(events))
        wait_for(lambda: len(receiver.received()) >= 10, "the failing receiver to be tried twice per event")
        receiver.stop()  # down: connections refused
        wait_for(
            lambda: all(any("refused" in (a.error or "").lower() for a in _attempts(sessions, d)) for d in events),
            "an attempt of every delivery against the closed port",
        )
        time.sleep(1.0)  # down a while longer: more retries are refused
        assert all(d.status == "pending" for d in _deliveries(sessions))
        receiver.default = Answer(200, b"thanks")
        receiver.start()  # back on the same port
        wait_for(lambda: all(d.status == "delivered" for d in _deliveries(sessions)), "every delivery delivered")
        assert worker.poll() is None
    finally:
        worker.send_signal(signal.SIGTERM)
        assert worker.wait(timeout=30) == 0
    requests = receiver.received()
    by_id: dict[str, list[Any]] = {}
    for request in requests:
        by_id.setdefault(request.webhook_id, []).append(request)
        request.verify(subscription["secret"])
    assert set(by_id) == {str(d.event_id) for d in _deliveries(sessions)}  # each event under its own id
    for delivery in _deliveries(sessions):
        log = _attempts(sessions, delivery.id)
        outcomes = [(a.outcome, a.status_code, "refused" in (a.error or "").lower()) for a in log]
        assert outcomes[0] == ("retry", 500, False) and outcomes[-1] == ("delivered", 200, False)
        assert ("retry", None, True) in outcomes  # tried while the receiver was down
        assert len(by_id[str(delivery.event_id)]) == sum(a.status_code is not None for a in log)
        assert [a.number for a in log] == list(range(1, len(log) + 1)) and delivery.attempts == len(log)


# --------------------------------------------------------------------------------------------------- recovery


def test_pending_deliveries_are_queued_again_when_a_worker_starts(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
) -> None:
    subscription = subscribe(api, receiver)
    events = _raise_events(sessions, subscription["id"], 3)  # committed, but Redis "lost" the jobs
    redis_dispatcher.deliveries_due(first_attempts(events[:1]))
    connection.flushall()
    settings = get_settings()
    assert requeue_pending(settings, redis_dispatcher).deliveries == 3
    assert requeue_pending(settings, redis_dispatcher).deliveries == 0  # already waiting: not queued twice
    run_jobs(connection)
    assert [d.status for d in _deliveries(sessions)] == ["delivered"] * 3
    assert len(receiver.received()) == 3


def test_a_scheduled_attempt_moves_to_the_newer_time_and_the_sweep_takes_only_overdue_ones(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
) -> None:
    subscription = subscribe(api, receiver)
    [delivery_id] = _raise_events(sessions, subscription["id"], 1)
    registry = ScheduledJobRegistry(WEBHOOKS_QUEUE, connection=connection)
    queue = Queue(WEBHOOKS_QUEUE, connection=connection)
    job_id = webhook_job_id(delivery_id, 1)
    later = datetime.now(UTC) + timedelta(hours=1)
    assert redis_dispatcher.deliveries_due([(delivery_id, 1, later)]) == 1
    assert registry.get_job_ids() == [job_id] and queue.count == 0
    assert redis_dispatcher.deliveries_due([(delivery_id, 1, None)]) == 1  # e.g. the subscription was re-enabled
    assert registry.get_job_ids() == [] and queue.job_ids == [job_id]
    assert redis_dispatcher.deliveries_due([(delivery_id, 1, None)]) == 0  # already queued to run
    connection.flushall()  # Redis lost it
    settings = get_settings()
    assert requeue_deliveries(settings, redis_dispatcher, overdue_only=True) == 0  # just raised: not overdue yet
    with sessions() as session, session.begin():
        session.get(WebhookDelivery, delivery_id).next_attempt_at = datetime.now(UTC) - timedelta(minutes=5)
    assert requeue_deliveries(settings, redis_dispatcher, overdue_only=True) == 1
    connection.flushall()
    with sessions() as session, session.begin():  # an attempt is out: it will schedule its own retry
        assert not isinstance(store.claim_attempt(session, delivery_id, 1, lease_s=60), str)
    assert requeue_deliveries(settings, redis_dispatcher, overdue_only=True) == 0


def test_a_worker_that_died_mid_attempt_leaves_an_interrupted_attempt_and_the_next_one_goes(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
) -> None:
    subscription = subscribe(api, receiver)
    [delivery_id] = _raise_events(sessions, subscription["id"], 1)
    past = datetime.now(UTC) - timedelta(minutes=10)
    with sessions() as session, session.begin():  # attempt 1 claimed 10 minutes ago by a worker that was killed
        claim = store.claim_attempt(session, delivery_id, 1, lease_s=60, now=past)
        assert not isinstance(claim, str)
    assert requeue_pending(get_settings(), redis_dispatcher).deliveries == 1  # its lease has run out: attempt 2 now
    run_jobs(connection)
    log = _attempts(sessions, delivery_id)
    assert [(a.number, a.outcome) for a in log] == [(1, "retry"), (2, "delivered")]
    assert "interrupted" in (log[0].error or "")


def test_an_attempt_that_starts_just_before_a_dead_attempts_lease_ends_waits_it_out(
    sessions: sessionmaker[Session], api: TestClient, receiver: Receiver
) -> None:
    """RQ schedules to the whole second, so the attempt queued for the end of a killed worker's lease may start
    before it ends: within the slack it waits and sends; with longer left, it leaves the delivery to its time."""
    subscription = subscribe(api, receiver)
    [soon, later] = _raise_events(sessions, subscription["id"], 2)
    now = datetime.now(UTC)
    with sessions() as session, session.begin():  # attempts 1 claimed by a worker that was then killed
        assert isinstance(
            store.claim_attempt(session, soon, 1, lease_s=61, now=now - timedelta(seconds=60)), store.Claim
        )
        assert isinstance(store.claim_attempt(session, later, 1, lease_s=60, now=now), store.Claim)
    started = time.monotonic()
    assert deliver_webhook(str(later), 2) == "skipped"
    assert deliver_webhook(str(soon), 2) == "delivered"
    assert 0.5 < time.monotonic() - started < 5.0  # waited out the second the lease had left
    assert [(a.number, a.outcome) for a in _attempts(sessions, soon)] == [(1, "retry"), (2, "delivered")]
    assert [(a.number, a.outcome) for a in _attempts(sessions, later)] == [(1, "sending")]


# --------------------------------------------------------------------------------------------------- deletions


def test_deleting_a_subscription_while_deliveries_are_pending_or_in_flight(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
) -> None:
    doomed = subscribe(api, receiver)
    kept = subscribe(api, receiver)
    queued = _raise_events(sessions, doomed["id"], 2)
    redis_dispatcher.deliveries_due(first_attempts(queued))
    [in_flight] = _raise_events(sessions, doomed["id"], 1)
    [survivor] = _raise_events(sessions, kept["id"], 1)
    redis_dispatcher.deliveries_due(first_attempts([survivor]))
    # One attempt is out when the subscription is deleted: the receiver answers slowly.
    receiver.answers.append(Answer(200, delay_s=1.5))

    def delete_doomed() -> None:
        with sessions() as session, session.begin():
            store.delete_subscription(session, uuid.UUID(doomed["id"]))

    deleter = threading.Timer(0.5, delete_doomed)
    deleter.start()
    assert deliver_webhook(str(in_flight), 1) == "gone"
    deleter.join()
    assert api.get(doomed["links"]["self"]).status_code == 404
    run_jobs(connection)  # the two queued jobs find nothing and end quietly; the worker carries on
    assert deliver_webhook(str(queued[0]), 1) == "gone"
    assert [(d.id, d.status) for d in _deliveries(sessions)] == [(survivor, "delivered")]
    assert Queue(WEBHOOKS_QUEUE, connection=connection).failed_job_registry.count == 0


def test_deleting_a_camera_does_not_recall_its_alerts(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
) -> None:
    camera = calibrated_camera(sessions, redis_dispatcher, connection)
    subscription = subscribe(api, receiver, event_types=["violation.detected"])
    receiver.stop()  # down: the alert stays pending
    post_people(sessions, redis_dispatcher, camera, close_pairs(camera)[0], T0)
    run_jobs(connection)
    [delivery] = _deliveries(sessions)
    assert delivery.status == "pending" and delivery.attempts == 1
    with sessions() as session, session.begin():
        assert delete_camera(session, camera.camera_id)
    receiver.start()
    assert deliver_webhook(str(delivery.id), 2) == "delivered"
    [alert] = payloads(receiver, subscription)
    assert alert["data"]["camera_id"] == camera.camera_id
    assert Queue(WEBHOOKS_QUEUE, connection=connection).failed_job_registry.count == 0


# --------------------------------------------------------------------------------------------------- receivers


def test_410_gone_disables_the_subscription_and_enabling_it_sends_what_waited(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
) -> None:
    subscription = subscribe(api, receiver)
    first, second = _raise_events(sessions, subscription["id"], 2)
    receiver.answers.append(Answer(410, b"gone"))
    assert deliver_webhook(str(first), 1) == "failed"
    got = api.get(subscription["links"]["self"]).json()
    assert got["enabled"] is False and "410" in got["disabled_reason"]
    assert deliver_webhook(str(second), 1) == "paused"  # held back, not sent, not failed
    assert len(receiver.received()) == 1
    assert api.patch(subscription["links"]["self"], json={"enabled": True}).json()["disabled_reason"] is None
    run_jobs(connection)
    assert {d.id: d.status for d in _deliveries(sessions)} == {first: "failed", second: "delivered"}


def test_the_address_is_checked_again_at_delivery_time(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    api: TestClient,
    receiver: Receiver,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Subscribed while loopback was allowed; the operator then closed it: the worker refuses to connect."""
    subscription = subscribe(api, receiver)
    [delivery_id] = _raise_events(sessions, subscription["id"], 1)
    monkeypatch.setenv("POSEMETRY_WEBHOOK_ALLOWED_NETWORKS", "")
    get_settings.cache_clear()
    counted = _delivery_counts()
    assert deliver_webhook(str(delivery_id), 1) == "failed"
    assert receiver.received() == []
    assert _delivery_counts() - counted == Counter(blocked=1)
    [attempt] = _attempts(sessions, delivery_id)
    assert attempt.outcome == "failed" and "SSRF" in (attempt.error or "") and "loopback" in (attempt.error or "")
    with sessions() as session:
        assert session.get(WebhookSubscription, uuid.UUID(subscription["id"])).enabled  # a policy refusal, not a 410
