"""Request and response bodies of the webhook routes (`/v1/webhooks`): subscriptions and their delivery log.

Secrets are write-once: a subscription's secret appears in the answer that created (or rotated) it and never
again, so a leaked listing or log does not leak it.
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field, StrictBool, field_validator

from service.http.schemas import CameraId, Integer, StrictModel
from service.store.webhook_models import DESCRIPTION_MAX_LENGTH, EVENT_TYPES, WEBHOOK_URL_MAX_LENGTH

from .signing import SECRET_DOCUMENTED_PATTERN, SECRET_PATTERN, secret_key

EventType = Literal["violation.detected", "calibration.updated", "calibration.status_changed"]
DeliveryStatus = Literal["pending", "delivered", "failed"]
AttemptOutcome = Literal["sending", "delivered", "retry", "failed"]
MAX_FILTER_CAMERAS = 1000
# How long a rotated-out secret keeps signing by default, and at most.
DEFAULT_ROTATION_GRACE_S = 24 * 3600
MAX_ROTATION_GRACE_S = 7 * 24 * 3600

Url = Field(
    min_length=1,
    max_length=WEBHOOK_URL_MAX_LENGTH,
    description="Where events are POSTed: http or https, on a public address (see the setting "
    "webhook_allowed_networks). Redirects are not followed.",
    examples=["https://alerts.example.com/posemetry"],
)
Secret = Field(
    default=None,
    pattern=SECRET_PATTERN,
    description="A Standard Webhooks secret `whsec_<base64 of 24-64 random bytes>`. Omitted: one is generated "
    "and returned once.",
    json_schema_extra={"pattern": SECRET_DOCUMENTED_PATTERN},
)


def _documented_without_null(schema: dict[str, Any]) -> None:
    """The JSON schema of a PATCH field that may be left out but not null: `None` is only its "not given" default
    (the model refuses an explicit null), so the document drops the null branch pydantic writes for `X | None`."""
    options = [option for option in schema.pop("anyOf", []) if option.get("type") != "null"]
    if len(options) == 1:
        schema.update(options[0])
    schema.pop("default", None)


def _unique(values: list[Any] | None) -> list[Any] | None:
    return None if values is None else list(dict.fromkeys(values))


def _check_secret(value: str | None) -> str | None:
    if value is not None:
        secret_key(value)  # raises ValueError with the reason
    return value


class WebhookCreate(StrictModel):
    """A new subscription (`POST /v1/webhooks`)."""

    url: str = Url
    secret: str | None = Secret
    event_types: list[EventType] = Field(
        default_factory=lambda: list(EVENT_TYPES),
        min_length=1,
        description="Events to send; default all three.",
    )
    camera_ids: list[CameraId] | None = Field(
        default=None,
        min_length=1,
        max_length=MAX_FILTER_CAMERAS,
        description="Only events of these cameras (they need not exist yet); null or absent: every camera.",
    )
    description: str | None = Field(default=None, max_length=DESCRIPTION_MAX_LENGTH)
    enabled: StrictBool = True

    _unique_lists = field_validator("event_types", "camera_ids")(_unique)
    _valid_secret = field_validator("secret")(_check_secret)


class WebhookUpdate(StrictModel):
    """Changes to a subscription (`PATCH`): only the fields given change; `camera_ids: null` means every camera.

    Re-enabling a subscription sends the deliveries that waited while it was disabled.
    """

    url: str | None = Field(
        default=None, min_length=1, max_length=WEBHOOK_URL_MAX_LENGTH, json_schema_extra=_documented_without_null
    )
    event_types: list[EventType] | None = Field(default=None, min_length=1, json_schema_extra=_documented_without_null)
    camera_ids: list[CameraId] | None = Field(default=None, min_length=1, max_length=MAX_FILTER_CAMERAS)
    description: str | None = Field(default=None, max_length=DESCRIPTION_MAX_LENGTH)
    enabled: StrictBool | None = Field(default=None, json_schema_extra=_documented_without_null)

    _unique_lists = field_validator("event_types", "camera_ids")(_unique)

    @field_validator("url", "event_types", "enabled")
    @classmethod
    def _not_null(cls, value: Any) -> Any:
        if value is None:
            raise ValueError("may be left out, but not null")
        return value


class SecretRotation(StrictModel):
    """A new secret (`POST /v1/webhooks/{id}/secret`); the old one keeps signing for `previous_valid_for_s`."""

    secret: str | None = Secret
    previous_valid_for_s: Integer = Field(
        default=DEFAULT_ROTATION_GRACE_S,
        ge=0,
        le=MAX_ROTATION_GRACE_S,
        description="Seconds during which deliveries carry a second signature made with the old secret, so "
        "receivers can switch over without losing messages (0: the old secret stops at once).",
    )

    _valid_secret = field_validator("secret")(_check_secret)


class WebhookOut(BaseModel):
    """A subscription (its secret is never shown again after creation or rotation)."""

    id: uuid.UUID
    url: str
    event_types: list[EventType]
    camera_ids: list[str] | None
    description: str | None
    enabled: bool
    disabled_reason: str | None = Field(description="Why posemetry disabled it (the receiver answered 410 Gone).")
    previous_secret_valid_until: datetime | None = Field(description="While set, the old secret also signs.")
    created_at: datetime
    updated_at: datetime
    links: dict[str, str]


class WebhookWithSecret(WebhookOut):
    """The answer to a creation or a rotation: the only time the secret is shown."""

    secret: str


class WebhookList(BaseModel):
    """Subscriptions oldest first; pass `next_after` as `after` for the next page (null: last page)."""

    items: list[WebhookOut]
    next_after: uuid.UUID | None


class AttemptOut(BaseModel):
    """One POST of a delivery and what came of it."""

    number: int
    started_at: datetime
    duration_s: float | None
    outcome: AttemptOutcome = Field(
        description="delivered; retry (a retry was scheduled); failed (not retried); sending (the request is out)."
    )
    status_code: int | None = Field(description="The receiver's HTTP status; null when no answer came.")
    error: str | None = Field(description="Why no answer came (connection refused, timeout, refused address).")
    response_body: str | None = Field(description="The start of the receiver's answer (see response_truncated).")
    response_truncated: bool
    peer: str | None = Field(description="The address connected to.")


class DeliveryOut(BaseModel):
    """One event sent to one subscription, retried until delivered or given up."""

    id: uuid.UUID
    subscription_id: uuid.UUID
    webhook_id: str = Field(description="The `webhook-id` header: the event's id, the same on every attempt.")
    event_type: EventType
    status: DeliveryStatus
    attempts: int
    next_attempt_at: datetime | None
    last_status_code: int | None
    last_error: str | None
    redelivery_of: uuid.UUID | None
    created_at: datetime
    finished_at: datetime | None
    url: str


class DeliveryDetail(DeliveryOut):
    """A delivery with its attempts (oldest first) and the exact body it sends."""

    attempt_log: list[AttemptOut]
    payload: dict[str, Any]


class DeliveryList(BaseModel):
    """Deliveries newest first; pass `next_before` as `before` for the next page (null: last page)."""

    items: list[DeliveryOut]
    next_before: uuid.UUID | None
