"""Webhook subscriptions, their delivery log and manual redelivery; the payloads in the OpenAPI `webhooks` section.

Subscribing checks the URL against the SSRF policy (service.webhooks.addresses) and answers 422 with the reason;
the delivery worker checks again on every connection.

Only admin keys manage subscriptions: a subscription sends camera data to an outside URL (all cameras' unless it
filters them), which is an operator's decision, not a camera system's.
"""

from __future__ import annotations

import json
import uuid
from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Response, status
from sqlalchemy.orm import Session

from service.dispatch import UNAVAILABLE_ERRORS, Dispatcher
from service.http.dependencies import DispatcherDep, ReadSessionDep, SessionDep, SettingsDep, queue_unavailable
from service.http.problems import ProblemError
from service.keys.dependencies import require_admin
from service.settings import Settings
from service.store.webhook_models import WebhookDelivery, WebhookSubscription
from service.webhooks import repository as store
from service.webhooks.addresses import AddressRefusedError, check_url
from service.webhooks.events import first_attempts
from service.webhooks.payloads import CalibrationStatusChanged, CalibrationUpdated, ViolationDetected
from service.webhooks.schemas import (
    AttemptOut,
    DeliveryDetail,
    DeliveryList,
    DeliveryOut,
    DeliveryStatus,
    SecretRotation,
    WebhookCreate,
    WebhookList,
    WebhookOut,
    WebhookUpdate,
    WebhookWithSecret,
)
from service.webhooks.signing import generate_secret

router = APIRouter(prefix="/v1/webhooks", tags=["webhooks"], dependencies=[Depends(require_admin)])


def webhook_url(subscription_id: uuid.UUID) -> str:
    return f"/v1/webhooks/{subscription_id}"


def delivery_url(subscription_id: uuid.UUID, delivery_id: uuid.UUID) -> str:
    return f"{webhook_url(subscription_id)}/deliveries/{delivery_id}"


def webhook_out(subscription: WebhookSubscription) -> WebhookOut:
    url = webhook_url(subscription.id)
    return WebhookOut(
        id=subscription.id,
        url=subscription.url,
        event_types=subscription.event_types,  # type: ignore[arg-type]
        camera_ids=subscription.camera_ids,
        description=subscription.description,
        enabled=subscription.enabled,
        disabled_reason=subscription.disabled_reason,
        previous_secret_valid_until=subscription.previous_secret_until if subscription.previous_secret else None,
        created_at=subscription.created_at,
        updated_at=subscription.updated_at,
        links={"self": url, "deliveries": f"{url}/deliveries"},
    )


def delivery_out(delivery: WebhookDelivery, event_type: str) -> DeliveryOut:
    return DeliveryOut(
        id=delivery.id,
        subscription_id=delivery.subscription_id,
        webhook_id=str(delivery.event_id),
        event_type=event_type,  # type: ignore[arg-type]
        status=delivery.status,  # type: ignore[arg-type]
        attempts=delivery.attempts,
        next_attempt_at=delivery.next_attempt_at,
        last_status_code=delivery.last_status_code,
        last_error=delivery.last_error,
        redelivery_of=delivery.redelivery_of,
        created_at=delivery.created_at,
        finished_at=delivery.finished_at,
        url=delivery_url(delivery.subscription_id, delivery.id),
    )


def _check_url(url: str, settings: Settings) -> None:
    """422 naming the field when the SSRF policy refuses the URL."""
    try:
        check_url(url, settings.webhook_allowed_networks)
    except AddressRefusedError as exc:
        message = f"refused: {exc}"
        raise ProblemError(
            422,
            "webhook-url-refused",
            f"Invalid request: body.url: {message}",
            errors=[{"loc": ["body", "url"], "field": "body.url", "msg": message, "type": "url_refused"}],
        ) from None


def _require(session: Session, subscription_id: uuid.UUID) -> WebhookSubscription:
    subscription = store.get_subscription(session, subscription_id)
    if subscription is None:
        raise ProblemError(404, "webhook-not-found", f"No webhook subscription {subscription_id}.")
    return subscription


def _queue(dispatcher: Dispatcher, due: list[tuple[uuid.UUID, int, datetime | None]], action: str) -> None:
    try:
        dispatcher.deliveries_due(due)
    except UNAVAILABLE_ERRORS as exc:
        raise queue_unavailable(f"{action} is stored and will be sent when the queue is back.", exc) from exc


@router.post("", status_code=status.HTTP_201_CREATED, response_model=WebhookWithSecret)
def create_webhook(
    body: WebhookCreate, response: Response, session: SessionDep, settings: SettingsDep
) -> WebhookWithSecret:
    """Subscribe a URL to events. The secret (given, or generated when omitted) is in this answer only."""
    _check_url(body.url, settings)
    secret = body.secret or generate_secret()
    subscription = store.create_subscription(
        session,
        url=body.url,
        secret=secret,
        event_types=body.event_types,
        camera_ids=body.camera_ids,
        description=body.description,
        enabled=body.enabled,
    )
    session.commit()
    response.headers["Location"] = webhook_url(subscription.id)
    return WebhookWithSecret(**webhook_out(subscription).model_dump(), secret=secret)


@router.get("", response_model=WebhookList)
def list_webhooks(
    session: ReadSessionDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Subscriptions per page.")] = 100,
    after: Annotated[uuid.UUID | None, Query(description="Last id of the previous page.")] = None,
) -> WebhookList:
    try:
        subscriptions = store.list_subscriptions(session, limit=limit, after=after)
    except store.SubscriptionNotFoundError:
        raise ProblemError(400, "bad-cursor", f"`after` names no subscription ({after}).") from None
    next_after = subscriptions[-1].id if len(subscriptions) == limit else None
    return WebhookList(items=[webhook_out(s) for s in subscriptions], next_after=next_after)


@router.get("/{subscription_id}", response_model=WebhookOut)
def get_webhook(subscription_id: uuid.UUID, session: ReadSessionDep) -> WebhookOut:
    return webhook_out(_require(session, subscription_id))


@router.patch("/{subscription_id}", response_model=WebhookOut)
def update_webhook(
    subscription_id: uuid.UUID,
    body: WebhookUpdate,
    session: SessionDep,
    settings: SettingsDep,
    dispatcher: DispatcherDep,
) -> WebhookOut:
    """Change a subscription; only the fields given change. Disabling holds its pending deliveries back;
    enabling sends them."""
    subscription = _require(session, subscription_id)
    changes = body.model_dump(include=body.model_fields_set)
    if "url" in changes:
        _check_url(changes["url"], settings)
    resumed = changes.get("enabled") is True and not subscription.enabled
    store.update_subscription(session, subscription, changes)
    waiting = store.subscription_pending_deliveries(session, subscription_id) if resumed else []
    session.commit()
    if waiting:
        _queue(dispatcher, [(d.delivery_id, d.attempt, None) for d in waiting], "the subscription is enabled; it")
    return webhook_out(subscription)


@router.post("/{subscription_id}/secret", response_model=WebhookWithSecret)
def rotate_webhook_secret(subscription_id: uuid.UUID, body: SecretRotation, session: SessionDep) -> WebhookWithSecret:
    """Replace the signing secret (given, or generated); the old one keeps signing as a second signature for
    `previous_valid_for_s`, so receivers can switch without dropping messages."""
    subscription = _require(session, subscription_id)
    secret = body.secret or generate_secret()
    store.rotate_secret(session, subscription, secret, grace_s=body.previous_valid_for_s)
    session.commit()
    return WebhookWithSecret(**webhook_out(subscription).model_dump(), secret=secret)


@router.delete("/{subscription_id}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response)
def delete_webhook(subscription_id: uuid.UUID, session: SessionDep) -> Response:
    """Delete a subscription with its delivery log; pending deliveries are dropped (never sent)."""
    _require(session, subscription_id)
    store.delete_subscription(session, subscription_id)
    session.commit()
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/{subscription_id}/deliveries", response_model=DeliveryList)
def list_webhook_deliveries(
    subscription_id: uuid.UUID,
    session: ReadSessionDep,
    status_: Annotated[
        DeliveryStatus | None, Query(alias="status", description="Only deliveries in this state.")
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="Deliveries per page.")] = 50,
    before: Annotated[uuid.UUID | None, Query(description="Last id of the previous page.")] = None,
) -> DeliveryList:
    """The subscription's delivery log, newest first."""
    _require(session, subscription_id)
    rows = store.list_deliveries(session, subscription_id, status=status_, limit=limit, before=before)
    next_before = rows[-1][0].id if len(rows) == limit else None
    return DeliveryList(items=[delivery_out(d, t) for d, t in rows], next_before=next_before)


@router.get("/{subscription_id}/deliveries/{delivery_id}", response_model=DeliveryDetail)
def get_webhook_delivery(subscription_id: uuid.UUID, delivery_id: uuid.UUID, session: ReadSessionDep) -> DeliveryDetail:
    """One delivery with every attempt (time, status code or error, duration, the start of the answer)."""
    found = store.get_delivery(session, subscription_id, delivery_id)
    if found is None:
        raise ProblemError(404, "delivery-not-found", f"No delivery {delivery_id} of webhook {subscription_id}.")
    delivery, event, attempts = found
    return DeliveryDetail(
        **delivery_out(delivery, event.type).model_dump(),
        attempt_log=[
            AttemptOut(
                number=a.number,
                started_at=a.started_at,
                duration_s=a.duration_s,
                outcome=a.outcome,  # type: ignore[arg-type]
                status_code=a.status_code,
                error=a.error,
                response_body=a.response_body,
                response_truncated=a.response_truncated,
                peer=a.peer,
            )
            for a in attempts
        ],
        payload=json.loads(event.body),
    )


@router.post(
    "/{subscription_id}/deliveries/{delivery_id}/redeliver",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=DeliveryOut,
)
def redeliver(
    subscription_id: uuid.UUID,
    delivery_id: uuid.UUID,
    response: Response,
    session: SessionDep,
    dispatcher: DispatcherDep,
) -> DeliveryOut:
    """Send the event again as a new delivery (same body, same `webhook-id`, a fresh retry budget), whatever
    became of the original; 202 with the new delivery."""
    subscription = _require(session, subscription_id)
    found = store.get_delivery(session, subscription_id, delivery_id)
    if found is None:
        raise ProblemError(404, "delivery-not-found", f"No delivery {delivery_id} of webhook {subscription_id}.")
    if not subscription.enabled:
        raise ProblemError(
            409, "webhook-disabled", f"Webhook {subscription_id} is disabled; enable it (PATCH) before redelivering."
        )
    delivery, event, _attempts = found
    again = store.redeliver(session, delivery)
    session.commit()
    response.headers["Location"] = delivery_url(subscription_id, again.id)
    _queue(dispatcher, first_attempts([again.id]), "the redelivery")
    return delivery_out(again, event.type)


# The bodies posemetry sends, for the OpenAPI document's `webhooks` section (FastAPI renders them; nothing is
# served). Receivers verify the Standard Webhooks signature headers before trusting a body.
callbacks = APIRouter()


@callbacks.post("violation.detected", summary="People stood closer than the camera's threshold")
def violation_detected(body: ViolationDetected) -> None:
    """One per frame with a pair under the threshold, after the per-pair cooldown."""


@callbacks.post("calibration.updated", summary="A new calibration version became current")
def calibration_updated(body: CalibrationUpdated) -> None:
    """Sent when a solve replaces the current calibration (or is the first one)."""


@callbacks.post("calibration.status_changed", summary="A camera became calibrated, or uncalibrated")
def calibration_status_changed(body: CalibrationStatusChanged) -> None:
    """Sent on a camera's first current calibration, and when a reset or a new image size drops it."""
