"""Every database operation on webhooks: subscriptions, events and their deliveries, attempts, cooldown state.

Like every repository, functions flush but never commit; the caller owns the transaction, so an event and its
deliveries are committed with whatever raised them (a frame's result, a calibration version) or not at all.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import TYPE_CHECKING, Any, cast

from sqlalchemy import Table, and_, delete, exists, insert, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.store.models import clip_reason, utc_now
from service.store.webhook_models import (
    ViolationCooldown,
    WebhookAttempt,
    WebhookDelivery,
    WebhookEvent,
    WebhookSubscription,
)

from .cooldown import AlertedPair, Cooldown

if TYPE_CHECKING:
    from .delivery import AttemptResult, Decision

_DELIVERIES = cast(Table, WebhookDelivery.__table__)
_COOLDOWNS = cast(Table, ViolationCooldown.__table__)
ERROR_MAX_LENGTH = 1000
INTERRUPTED = "interrupted: the worker stopped before the answer was recorded"


class SubscriptionNotFoundError(LookupError):
    """No webhook subscription with that id."""


# --------------------------------------------------------------------------------------------------- subscriptions


def create_subscription(
    session: Session,
    *,
    url: str,
    secret: str,
    event_types: Sequence[str],
    camera_ids: Sequence[str] | None,
    description: str | None = None,
    enabled: bool = True,
    now: datetime | None = None,
) -> WebhookSubscription:
    now = now or utc_now()
    subscription = WebhookSubscription(
        id=uuid.uuid4(),
        url=url,
        secret=secret,
        event_types=list(event_types),
        camera_ids=None if camera_ids is None else list(camera_ids),
        description=description,
        enabled=enabled,
        created_at=now,
        updated_at=now,
    )
    session.add(subscription)
    session.flush()
    return subscription


def get_subscription(session: Session, subscription_id: uuid.UUID) -> WebhookSubscription | None:
    return session.get(WebhookSubscription, subscription_id)


def list_subscriptions(
    session: Session, *, limit: int = 100, after: uuid.UUID | None = None
) -> list[WebhookSubscription]:
    """Subscriptions oldest first, a page at a time (pass the last id of a page as `after`)."""
    stmt = select(WebhookSubscription).order_by(WebhookSubscription.created_at, WebhookSubscription.id).limit(limit)
    if after is not None:
        last = session.get(WebhookSubscription, after)
        if last is None:
            raise SubscriptionNotFoundError(str(after))
        stmt = stmt.where(
            or_(
                WebhookSubscription.created_at > last.created_at,
                and_(WebhookSubscription.created_at == last.created_at, WebhookSubscription.id > last.id),
            )
        )
    return list(session.scalars(stmt))


def update_subscription(
    session: Session, subscription: WebhookSubscription, changes: dict[str, Any], *, now: datetime | None = None
) -> WebhookSubscription:
    """Apply field changes (url, event_types, camera_ids, description, enabled); enabling clears the reason it
    was disabled for."""
    for name, value in changes.items():
        setattr(subscription, name, list(value) if isinstance(value, tuple) else value)
    if changes.get("enabled") is True:
        subscription.disabled_reason = None
    subscription.updated_at = now or utc_now()
    session.flush()
    return subscription


def rotate_secret(
    session: Session, subscription: WebhookSubscription, secret: str, *, grace_s: float, now: datetime | None = None
) -> WebhookSubscription:
    """Replace the secret; the old one keeps signing (as a second signature) for `grace_s` seconds."""
    now = now or utc_now()
    subscription.previous_secret = subscription.secret if grace_s > 0 else None
    subscription.previous_secret_until = now + timedelta(seconds=grace_s) if grace_s > 0 else None
    subscription.secret = secret
    subscription.updated_at = now
    session.flush()
    return subscription


def delete_subscription(session: Session, subscription_id: uuid.UUID) -> bool:
    """Delete a subscription and, by cascade, its deliveries and their attempts (pending ones included)."""
    result = session.execute(delete(WebhookSubscription).where(WebhookSubscription.id == subscription_id))
    return bool(result.rowcount)  # type: ignore[attr-defined]


def subscriptions_for(session: Session, event_type: str, camera_id: str) -> list[WebhookSubscription]:
    """Enabled subscriptions that want `event_type` from `camera_id`.

    Filtered in Python: there are a handful of subscriptions, and JSON membership tests differ by backend.
    """
    enabled = session.scalars(select(WebhookSubscription).where(WebhookSubscription.enabled.is_(True)))
    return [s for s in enabled if event_type in s.event_types and (s.camera_ids is None or camera_id in s.camera_ids)]


# --------------------------------------------------------------------------------------------------- events


def raise_event(
    session: Session,
    *,
    event_type: str,
    camera_id: str,
    body: str,
    subscriptions: Sequence[WebhookSubscription],
    dedupe_key: str | None = None,
    now: datetime | None = None,
) -> list[uuid.UUID]:
    """Store an event and one pending delivery per subscription; returns the deliveries' ids (to queue after
    commit). Nothing is stored without subscriptions, or when an event with the same `dedupe_key` exists."""
    if not subscriptions:
        return []
    now = now or utc_now()
    if dedupe_key is not None and session.scalar(select(exists().where(WebhookEvent.dedupe_key == dedupe_key))):
        return []
    event = WebhookEvent(
        id=uuid.uuid4(), type=event_type, camera_id=camera_id, dedupe_key=dedupe_key, body=body, created_at=now
    )
    try:
        with session.begin_nested():
            session.add(event)
            session.flush()
    except IntegrityError:
        if dedupe_key is not None and session.scalar(select(exists().where(WebhookEvent.dedupe_key == dedupe_key))):
            return []  # raised concurrently by another transaction
        raise
    rows = [
        {
            "id": uuid.uuid4(),
            "subscription_id": s.id,
            "event_id": event.id,
            "status": "pending",
            "attempts": 0,
            "next_attempt_at": now,
            "created_at": now,
        }
        for s in subscriptions
    ]
    session.execute(insert(_DELIVERIES), rows)
    return [row["id"] for row in rows]


# --------------------------------------------------------------------------------------------------- cooldown


def load_cooldown(session: Session, camera_id: str, *, since: datetime, window_s: float, radius_m: float) -> Cooldown:
    """The camera's alerted pairs from `since` on, as a Cooldown to apply to new frames."""
    rows = session.scalars(
        select(ViolationCooldown)
        .where(ViolationCooldown.camera_id == camera_id, ViolationCooldown.alerted_at >= since)
        .order_by(ViolationCooldown.alerted_at)
    )
    pairs = [AlertedPair(r.alerted_at, (r.a_x_m, r.a_y_m), (r.b_x_m, r.b_y_m), row_id=r.id) for r in rows]
    return Cooldown(pairs, window_s=window_s, radius_m=radius_m)


def save_cooldown(session: Session, camera_id: str, cooldown: Cooldown, *, forget_before: datetime) -> None:
    """Write back moved pairs, insert new ones, and forget alerts too old to silence anything."""
    for pair in cooldown.alerted:
        values = {"a_x_m": pair.a[0], "a_y_m": pair.a[1], "b_x_m": pair.b[0], "b_y_m": pair.b[1]}
        if pair.row_id is None:
            session.execute(insert(_COOLDOWNS), [{"camera_id": camera_id, "alerted_at": pair.alerted_at, **values}])
        elif pair.moved:
            session.execute(update(_COOLDOWNS).where(_COOLDOWNS.c.id == pair.row_id).values(**values))
    session.execute(
        delete(ViolationCooldown).where(
            ViolationCooldown.camera_id == camera_id, ViolationCooldown.alerted_at < forget_before
        )
    )


# --------------------------------------------------------------------------------------------------- attempts


@dataclass(frozen=True)
class Claim:
    """An attempt this job owns: what to send, where, signed with which secrets."""

    delivery_id: uuid.UUID
    attempt: int
    url: str
    secrets: tuple[str, ...]
    message_id: str
    body: bytes


@dataclass(frozen=True)
class Leased:
    """The attempt before is still out, or its worker died and its lease has not run out: for `left_s` more seconds,
    measured on the clock the claim was judged by (a second reading could find the lease just over, and the attempt
    neither taken nor waited for)."""

    left_s: float


def claim_attempt(
    session: Session, delivery_id: uuid.UUID, attempt: int, *, lease_s: float, now: datetime | None = None
) -> Claim | Leased | str:
    """Take attempt number `attempt` of a delivery, or say why not: `gone` (deleted), `skipped` (no longer
    pending, or that attempt already taken), `Leased` (the attempt before still holds its lease) or `paused`
    (subscription disabled).

    The claim is a conditional UPDATE (attempts must still be attempt - 1, and no lease running), so of two jobs
    racing for one attempt only one sends. An attempt left `sending` by a worker that died is closed as
    interrupted here, and counts as used.
    """
    now = now or utc_now()
    delivery = session.get(WebhookDelivery, delivery_id)
    if delivery is None:
        return "gone"
    if delivery.status != "pending" or delivery.attempts != attempt - 1:
        return "skipped"
    if delivery.lease_until is not None and delivery.lease_until > now:
        return Leased((delivery.lease_until - now).total_seconds())
    subscription = session.get(WebhookSubscription, delivery.subscription_id)
    event = session.get(WebhookEvent, delivery.event_id)
    if subscription is None or event is None:
        return "gone"
    if not subscription.enabled:
        return "paused"
    claimed = session.execute(
        update(_DELIVERIES)
        .where(
            _DELIVERIES.c.id == delivery_id,
            _DELIVERIES.c.status == "pending",
            _DELIVERIES.c.attempts == attempt - 1,
            or_(_DELIVERIES.c.lease_until.is_(None), _DELIVERIES.c.lease_until <= now),
        )
        .values(attempts=attempt, lease_until=now + timedelta(seconds=lease_s))
    )
    if not claimed.rowcount:  # type: ignore[attr-defined]
        return "skipped"
    session.execute(
        update(WebhookAttempt)
        .where(WebhookAttempt.delivery_id == delivery_id, WebhookAttempt.outcome == "sending")
        .values(outcome="retry", error=INTERRUPTED)
    )
    session.add(WebhookAttempt(delivery_id=delivery_id, number=attempt, started_at=now, outcome="sending"))
    session.flush()
    secrets = [subscription.secret]
    if subscription.previous_secret and subscription.previous_secret_until and subscription.previous_secret_until > now:
        secrets.append(subscription.previous_secret)
    return Claim(delivery_id, attempt, subscription.url, tuple(secrets), str(event.id), event.body.encode())


@dataclass(frozen=True)
class AttemptRecord:
    """How an attempt ended (its answer, or what prevented one), what that means for its delivery, and when the
    next attempt may start (a retry)."""

    result: AttemptResult
    decision: Decision
    next_attempt_at: datetime | None = None


def record_attempt(
    session: Session, delivery_id: uuid.UUID, attempt: int, record: AttemptRecord, *, now: datetime | None = None
) -> bool:
    """Store an attempt's answer and move its delivery on; False when the delivery was deleted meanwhile."""
    now = now or utc_now()
    result, decision = record.result, record.decision
    updated = session.execute(
        update(WebhookAttempt)
        .where(WebhookAttempt.delivery_id == delivery_id, WebhookAttempt.number == attempt)
        .values(
            outcome=decision.outcome,
            duration_s=result.duration_s,
            status_code=result.status_code,
            error=None if result.error is None else clip_reason(result.error, ERROR_MAX_LENGTH),
            response_body=result.response_body,
            response_truncated=result.response_truncated,
            peer=result.peer,
        )
    )
    if not updated.rowcount:  # type: ignore[attr-defined]
        return False
    finished = decision.outcome in ("delivered", "failed")
    session.execute(
        update(_DELIVERIES)
        .where(_DELIVERIES.c.id == delivery_id)
        .values(
            status="pending" if decision.outcome == "retry" else decision.outcome,
            lease_until=None,
            next_attempt_at=record.next_attempt_at if decision.outcome == "retry" else None,
            last_status_code=result.status_code,
            last_error=None if decision.reason is None else clip_reason(decision.reason, ERROR_MAX_LENGTH),
            finished_at=now if finished else None,
        )
    )
    if decision.disable_subscription is not None:
        subscription_id = select(WebhookDelivery.subscription_id).where(WebhookDelivery.id == delivery_id)
        session.execute(
            update(WebhookSubscription)
            .where(WebhookSubscription.id == subscription_id.scalar_subquery())
            .values(enabled=False, disabled_reason=decision.disable_subscription, updated_at=now)
        )
    return True


# --------------------------------------------------------------------------------------------------- the log


def list_deliveries(
    session: Session,
    subscription_id: uuid.UUID,
    *,
    status: str | None = None,
    limit: int = 50,
    before: uuid.UUID | None = None,
) -> list[tuple[WebhookDelivery, str]]:
    """A subscription's deliveries newest first with their event type, a page at a time (`before`: the last id
    of the previous page)."""
    stmt = (
        select(WebhookDelivery, WebhookEvent.type)
        .join(WebhookEvent, WebhookEvent.id == WebhookDelivery.event_id)
        .where(WebhookDelivery.subscription_id == subscription_id)
        .order_by(WebhookDelivery.created_at.desc(), WebhookDelivery.id.desc())
        .limit(limit)
    )
    if status is not None:
        stmt = stmt.where(WebhookDelivery.status == status)
    if before is not None:
        last = session.get(WebhookDelivery, before)
        if last is not None:
            stmt = stmt.where(
                or_(
                    WebhookDelivery.created_at < last.created_at,
                    and_(WebhookDelivery.created_at == last.created_at, WebhookDelivery.id < last.id),
                )
            )
    return [(delivery, event_type) for delivery, event_type in session.execute(stmt)]


def get_delivery(
    session: Session, subscription_id: uuid.UUID, delivery_id: uuid.UUID
) -> tuple[WebhookDelivery, WebhookEvent, list[WebhookAttempt]] | None:
    """One delivery of that subscription with its event and attempts (oldest first)."""
    delivery = session.get(WebhookDelivery, delivery_id)
    if delivery is None or delivery.subscription_id != subscription_id:
        return None
    event = session.get(WebhookEvent, delivery.event_id)
    if event is None:
        return None
    attempts = session.scalars(
        select(WebhookAttempt).where(WebhookAttempt.delivery_id == delivery_id).order_by(WebhookAttempt.number)
    )
    return delivery, event, list(attempts)


def redeliver(session: Session, delivery: WebhookDelivery, *, now: datetime | None = None) -> WebhookDelivery:
    """A new pending delivery of the same event to the same subscription (same webhook-id), with a fresh retry
    budget; the original keeps its log."""
    now = now or utc_now()
    again = WebhookDelivery(
        id=uuid.uuid4(),
        subscription_id=delivery.subscription_id,
        event_id=delivery.event_id,
        status="pending",
        attempts=0,
        next_attempt_at=now,
        redelivery_of=delivery.id,
        created_at=now,
    )
    session.add(again)
    session.flush()
    return again


@dataclass(frozen=True)
class DueDelivery:
    """A pending delivery's next attempt: its number, and when it may start (None: now)."""

    delivery_id: uuid.UUID
    attempt: int
    at: datetime | None


def pending_deliveries(
    session: Session, *, limit: int = 1000, after: uuid.UUID | None = None, due_before: datetime | None = None
) -> list[DueDelivery]:
    """Pending deliveries of enabled subscriptions (worker start-up, the sweep), in id order a page at a time.

    The next attempt may start at its scheduled time, or when a lease left by a worker that died runs out.
    `due_before` (the sweep) keeps only deliveries whose next attempt was due before then and that no attempt
    holds a lease on: an attempt in flight schedules its own retry.
    """
    stmt = (
        select(
            WebhookDelivery.id, WebhookDelivery.attempts, WebhookDelivery.next_attempt_at, WebhookDelivery.lease_until
        )
        .join(WebhookSubscription, WebhookSubscription.id == WebhookDelivery.subscription_id)
        .where(WebhookDelivery.status == "pending", WebhookSubscription.enabled.is_(True))
        .order_by(WebhookDelivery.id)
        .limit(limit)
    )
    if after is not None:
        stmt = stmt.where(WebhookDelivery.id > after)
    if due_before is not None:
        stmt = stmt.where(
            or_(WebhookDelivery.next_attempt_at.is_(None), WebhookDelivery.next_attempt_at < due_before),
            or_(WebhookDelivery.lease_until.is_(None), WebhookDelivery.lease_until < due_before),
        )
    due = []
    for delivery_id, attempts, next_attempt_at, lease_until in session.execute(stmt):
        times = [t for t in (next_attempt_at, lease_until) if t is not None]
        due.append(DueDelivery(delivery_id, int(attempts) + 1, max(times) if times else None))
    return due


def subscription_pending_deliveries(session: Session, subscription_id: uuid.UUID) -> list[DueDelivery]:
    """A subscription's pending deliveries (to queue again when it is re-enabled)."""
    rows = session.execute(
        select(WebhookDelivery.id, WebhookDelivery.attempts).where(
            WebhookDelivery.subscription_id == subscription_id, WebhookDelivery.status == "pending"
        )
    )
    return [DueDelivery(delivery_id, int(attempts) + 1, None) for delivery_id, attempts in rows]


def prune_webhook_log(session: Session, *, before: datetime) -> int:
    """Delete events raised before `before` (with their deliveries and attempts) unless one is still pending."""
    still_pending = exists().where(WebhookDelivery.event_id == WebhookEvent.id, WebhookDelivery.status == "pending")
    result = session.execute(delete(WebhookEvent).where(WebhookEvent.created_at < before, ~still_pending))
    return int(result.rowcount)  # type: ignore[attr-defined]
