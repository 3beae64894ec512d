"""The SQL schema of webhooks: subscriptions, the events raised, one delivery per event and subscription, every
delivery attempt, and the per-camera cooldown of violation alerts.

Design choices the delivery worker relies on:

- SQL is the truth, Redis only a reminder: an event and its deliveries are committed before any job is queued,
  and a delivery's state (`pending` with `next_attempt_at`, `delivered`, `failed`) says what is left to do, so a
  worker starting (or the periodic sweep) can queue whatever Redis lost.
- An event's body is stored as the exact JSON text that is signed and sent, so every retry and redelivery of it
  sends the same bytes under the same `webhook-id` (the event id).
- An attempt is claimed in SQL before the request goes out (`attempts` moves on and a lease is taken), so a job
  that runs twice, or two workers that pick up the same delivery, never send one attempt twice; an attempt whose
  worker died mid-request stays in the log with outcome `sending`.
- Events do not reference cameras: an alert already raised is not recalled when its camera is deleted, and the
  delivery log stays an honest record of what was sent. Cooldown state is per camera and goes with it.
"""

from __future__ import annotations

import uuid
from datetime import datetime

from sqlalchemy import JSON, Boolean, CheckConstraint, ForeignKey, Index, Integer, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from .models import CAMERA_ID_MAX_LENGTH, Base, BigIntegerKey, _in, utc_now

EVENT_TYPES = ("violation.detected", "calibration.updated", "calibration.status_changed")
DELIVERY_STATUSES = ("pending", "delivered", "failed")
# sending: the request is out (or its worker died before recording the answer).
ATTEMPT_OUTCOMES = ("sending", "delivered", "retry", "failed")
WEBHOOK_URL_MAX_LENGTH = 2048
DESCRIPTION_MAX_LENGTH = 500
EVENT_DEDUPE_KEY_MAX_LENGTH = 200


class WebhookSubscription(Base):
    """Where to send which events, signed with which secret."""

    __tablename__ = "webhook_subscriptions"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=uuid.uuid4)
    url: Mapped[str] = mapped_column(String(WEBHOOK_URL_MAX_LENGTH))
    # The Standard Webhooks `whsec_<base64>` secret. Stored as is: signing needs the secret itself, not a hash.
    secret: Mapped[str]
    # After a rotation the old secret also signs (a second signature) until previous_secret_until.
    previous_secret: Mapped[str | None]
    previous_secret_until: Mapped[datetime | None]
    event_types: Mapped[list[str]] = mapped_column(JSON)
    # None: every camera; else the camera ids whose events are sent (cameras need not exist yet).
    camera_ids: Mapped[list[str] | None] = mapped_column(JSON)
    description: Mapped[str | None] = mapped_column(String(DESCRIPTION_MAX_LENGTH))
    enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    disabled_reason: Mapped[str | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(default=utc_now)


class WebhookEvent(Base):
    """Something a subscriber may want to hear about, with the exact body its deliveries send."""

    __tablename__ = "webhook_events"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=uuid.uuid4)
    type: Mapped[str] = mapped_column(String(32))
    camera_id: Mapped[str] = mapped_column(String(CAMERA_ID_MAX_LENGTH))
    # Raising the same event twice (a frame measured again, say) is a no-op: NULLs are distinct, so events
    # without a natural key never clash.
    dedupe_key: Mapped[str | None] = mapped_column(String(EVENT_DEDUPE_KEY_MAX_LENGTH), unique=True)
    body: Mapped[str]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)

    __table_args__ = (
        CheckConstraint(f"type IN {_in(EVENT_TYPES)}", name="type"),
        # Pruning the log by age.
        Index("ix_webhook_events_created_at", "created_at"),
    )


class WebhookDelivery(Base):
    """One event to one subscription: retried until delivered or given up; its attempts are the log."""

    __tablename__ = "webhook_deliveries"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=uuid.uuid4)
    subscription_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("webhook_subscriptions.id", ondelete="CASCADE"))
    event_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("webhook_events.id", ondelete="CASCADE"))
    status: Mapped[str] = mapped_column(String(16), default="pending")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[datetime | None]
    # While an attempt is out: no other job may claim this delivery before the lease ends.
    lease_until: Mapped[datetime | None]
    last_status_code: Mapped[int | None] = mapped_column(Integer)
    last_error: Mapped[str | None]
    # A manual redelivery is a new delivery of the same event (same webhook-id) pointing back at the original.
    redelivery_of: Mapped[uuid.UUID | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    finished_at: Mapped[datetime | None]

    __table_args__ = (
        CheckConstraint(f"status IN {_in(DELIVERY_STATUSES)}", name="status"),
        CheckConstraint("attempts >= 0", name="attempts_non_negative"),
        # A subscription's log, newest first.
        Index("ix_webhook_deliveries_subscription_id_created_at", "subscription_id", "created_at"),
        # What is left to do (worker start-up, the sweep); also the cascade's index from events.
        Index("ix_webhook_deliveries_status_next_attempt_at", "status", "next_attempt_at"),
        Index("ix_webhook_deliveries_event_id", "event_id"),
    )


class WebhookAttempt(Base):
    """One HTTP request of a delivery and what came of it."""

    __tablename__ = "webhook_attempts"

    id: Mapped[int] = mapped_column(BigIntegerKey, primary_key=True, autoincrement=True)
    delivery_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("webhook_deliveries.id", ondelete="CASCADE"))
    number: Mapped[int] = mapped_column(Integer)
    started_at: Mapped[datetime]
    duration_s: Mapped[float | None]
    outcome: Mapped[str] = mapped_column(String(16), default="sending")
    status_code: Mapped[int | None] = mapped_column(Integer)
    error: Mapped[str | None]
    # The receiver's answer, cut to the first RESPONSE_LOG_BYTES bytes (response_truncated says when it was).
    response_body: Mapped[str | None]
    response_truncated: Mapped[bool] = mapped_column(Boolean, default=False)
    # The address actually connected to, as ip:port (the SSRF check is made on it).
    peer: Mapped[str | None] = mapped_column(String(64))

    __table_args__ = (
        UniqueConstraint("delivery_id", "number"),
        CheckConstraint(f"outcome IN {_in(ATTEMPT_OUTCOMES)}", name="outcome"),
        CheckConstraint("number >= 1", name="number_positive"),
    )


class ViolationCooldown(Base):
    """A pair of people a violation alert was raised for: where they stood (last seen), and when it fired.

    Ground positions are the frame result's `ground_m` (metres on the ground plane), so "the same pair" is decided
    by where people stand, without tracking anyone across frames (see service.webhooks.cooldown).
    """

    __tablename__ = "violation_cooldowns"

    id: Mapped[int] = mapped_column(BigIntegerKey, primary_key=True, autoincrement=True)
    camera_id: Mapped[str] = mapped_column(String(CAMERA_ID_MAX_LENGTH), ForeignKey("cameras.id", ondelete="CASCADE"))
    alerted_at: Mapped[datetime]
    a_x_m: Mapped[float]
    a_y_m: Mapped[float]
    b_x_m: Mapped[float]
    b_y_m: Mapped[float]

    __table_args__ = (Index("ix_violation_cooldowns_camera_id_alerted_at", "camera_id", "alerted_at"),)
