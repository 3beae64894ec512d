"""The webhook tables on SQLite and PostgreSQL: events raised once, attempts claimed once, leases, the sweep's
query, the cooldown round trip, cascades, and pruning the log."""

from __future__ import annotations

import uuid
from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session

from service.cameras.repository import delete_camera, upsert_camera
from service.store import WebhookAttempt, WebhookDelivery, WebhookEvent, make_session_factory
from service.store.webhook_models import ViolationCooldown
from service.webhooks import repository as store
from service.webhooks.cooldown import Candidate
from service.webhooks.delivery import AttemptResult, Decision
from service.webhooks.signing import generate_secret

# A 200 answer, recorded.
DELIVERED = store.AttemptRecord(AttemptResult(0.1, status_code=200), Decision("delivered"))

pytestmark = pytest.mark.both_backends

NOW = datetime(2026, 3, 1, 12, tzinfo=UTC)
BODY = '{"type":"calibration.updated","timestamp":"2026-03-01T12:00:00Z","data":{}}'


def _subscription(session: Session, **fields: object) -> store.WebhookSubscription:
    values = {
        "url": "https://hooks.example/x",
        "secret": generate_secret(),
        "event_types": ["calibration.updated"],
        "camera_ids": None,
    }
    return store.create_subscription(session, **{**values, **fields})  # type: ignore[arg-type]


def _raise(session: Session, subscriptions: list[store.WebhookSubscription], **kwargs: object) -> list[uuid.UUID]:
    return store.raise_event(
        session, event_type="calibration.updated", camera_id="cam", body=BODY, subscriptions=subscriptions, **kwargs
    )  # type: ignore[arg-type]


def test_events_need_subscribers_and_are_raised_once_per_key(session: Session) -> None:
    assert _raise(session, []) == []
    a, b = _subscription(session), _subscription(session)
    deliveries = _raise(session, [a, b], dedupe_key="calibration:cam:1")
    assert len(deliveries) == 2
    assert _raise(session, [a, b], dedupe_key="calibration:cam:1") == []  # a job that ran twice
    assert len(_raise(session, [a])) == 1  # no key: always a new event
    session.commit()
    assert session.scalar(select(func.count()).select_from(WebhookEvent)) == 2


def test_subscriptions_for_filters_type_camera_and_enabled(session: Session) -> None:
    everything = _subscription(session, event_types=["calibration.updated", "violation.detected"])
    lobby = _subscription(session, event_types=["violation.detected"], camera_ids=["lobby"])
    off = _subscription(session, event_types=["violation.detected"], enabled=False)
    assert {s.id for s in store.subscriptions_for(session, "violation.detected", "lobby")} == {everything.id, lobby.id}
    assert {s.id for s in store.subscriptions_for(session, "violation.detected", "door")} == {everything.id}
    assert store.subscriptions_for(session, "calibration.status_changed", "lobby") == []
    assert off.id not in {s.id for s in store.subscriptions_for(session, "violation.detected", "x")}


def test_an_attempt_is_claimed_once_and_leased(engine: Engine) -> None:
    sessions = make_session_factory(engine)
    with sessions() as session, session.begin():
        [delivery_id] = _raise(session, [_subscription(session)], now=NOW)
    with sessions() as first, first.begin():
        claim = store.claim_attempt(first, delivery_id, 1, lease_s=60, now=NOW)
        assert isinstance(claim, store.Claim) and claim.message_id and claim.body == BODY.encode()
    with sessions() as session, session.begin():
        assert store.claim_attempt(session, delivery_id, 1, lease_s=60, now=NOW) == "skipped"  # taken
        leased = store.claim_attempt(session, delivery_id, 2, lease_s=60, now=NOW + timedelta(seconds=45))
        assert leased == store.Leased(15.0)  # attempt 1 is out: its lease has 15 s to run
        assert store.claim_attempt(session, uuid.uuid4(), 1, lease_s=60, now=NOW) == "gone"
    with sessions() as session:
        [due] = store.pending_deliveries(session)
        assert (due.attempt, due.at) == (2, NOW + timedelta(seconds=60))  # after the lease
        # The sweep looks only at what is overdue.
        assert store.pending_deliveries(session, due_before=NOW - timedelta(seconds=1)) == []
    retry_at = NOW + timedelta(seconds=5)
    with sessions() as session, session.begin():
        answer = AttemptResult(0.2, status_code=503)
        record = store.AttemptRecord(answer, Decision("retry", reason="HTTP 503"), next_attempt_at=retry_at)
        assert store.record_attempt(session, delivery_id, 1, record, now=NOW)
    with sessions() as session:
        [due] = store.pending_deliveries(session)
        assert (due.attempt, due.at) == (2, retry_at)
        delivery = session.get(WebhookDelivery, delivery_id)
        assert delivery is not None and delivery.lease_until is None and delivery.last_error == "HTTP 503"
    with sessions() as session, session.begin():
        assert isinstance(store.claim_attempt(session, delivery_id, 2, lease_s=60, now=retry_at), store.Claim)
        assert store.record_attempt(session, delivery_id, 2, DELIVERED, now=retry_at)
    with sessions() as session:
        assert store.pending_deliveries(session) == []
        delivery = session.get(WebhookDelivery, delivery_id)
        assert delivery is not None and (delivery.status, delivery.attempts) == ("delivered", 2)
        assert delivery.finished_at == retry_at


def test_deleting_the_subscription_takes_its_deliveries_and_attempts(session: Session) -> None:
    subscription = _subscription(session)
    [delivery_id] = _raise(session, [subscription])
    store.claim_attempt(session, delivery_id, 1, lease_s=60)
    session.commit()
    assert store.delete_subscription(session, subscription.id)
    session.commit()
    assert session.scalar(select(func.count()).select_from(WebhookDelivery)) == 0
    assert session.scalar(select(func.count()).select_from(WebhookAttempt)) == 0
    assert not store.record_attempt(session, delivery_id, 1, DELIVERED)


def test_cooldown_round_trip_and_camera_cascade(session: Session) -> None:
    upsert_camera(session, "cam", image_width_px=640, image_height_px=480, person_height_m=1.3)
    cooldown = store.load_cooldown(session, "cam", since=NOW - timedelta(hours=1), window_s=60, radius_m=1.0)
    assert cooldown.admit(NOW, [Candidate(0, 1, (0.0, 5.0), (1.0, 5.0))])
    store.save_cooldown(session, "cam", cooldown, forget_before=NOW - timedelta(seconds=60))
    session.commit()
    later = NOW + timedelta(seconds=10)
    reloaded = store.load_cooldown(session, "cam", since=later - timedelta(seconds=60), window_s=60, radius_m=1.0)
    assert reloaded.admit(later, [Candidate(0, 1, (0.5, 5.5), (1.5, 5.5))]) == []  # moved half a metre
    store.save_cooldown(session, "cam", reloaded, forget_before=later - timedelta(seconds=60))
    session.commit()
    [row] = session.scalars(select(ViolationCooldown)).all()
    assert (row.a_x_m, row.b_x_m, row.alerted_at) == (0.5, 1.5, NOW)  # last seen moved, alert time kept
    much_later = NOW + timedelta(hours=1)
    store.save_cooldown(
        session, "cam", store.load_cooldown(session, "cam", since=NOW, window_s=60, radius_m=1.0),
        forget_before=much_later - timedelta(seconds=60),
    )  # fmt: skip
    assert session.scalar(select(func.count()).select_from(ViolationCooldown)) == 0
    cooldown = store.load_cooldown(session, "cam", since=NOW, window_s=60, radius_m=1.0)
    cooldown.admit(NOW, [Candidate(0, 1, (0.0, 5.0), (1.0, 5.0))])
    store.save_cooldown(session, "cam", cooldown, forget_before=NOW - timedelta(seconds=60))
    _raise(session, [_subscription(session)])
    session.commit()
    assert delete_camera(session, "cam")
    session.commit()
    assert session.scalar(select(func.count()).select_from(ViolationCooldown)) == 0
    assert session.scalar(select(func.count()).select_from(WebhookEvent)) == 1  # raised alerts stay


def test_pruning_keeps_recent_and_pending_events(session: Session) -> None:
    subscription = _subscription(session)
    old_done, old_pending, recent = (_raise(session, [subscription], now=NOW - timedelta(days=d)) for d in (40, 40, 1))
    for delivery_id in (*old_done, *recent):
        store.claim_attempt(session, delivery_id, 1, lease_s=60)
        store.record_attempt(session, delivery_id, 1, DELIVERED)
    session.commit()
    assert store.prune_webhook_log(session, before=NOW - timedelta(days=30)) == 1
    session.commit()
    left = set(session.scalars(select(WebhookDelivery.id)))
    assert left == {*old_pending, *recent}
    assert session.scalar(select(func.count()).select_from(WebhookAttempt)) == 1  # the recent one's
