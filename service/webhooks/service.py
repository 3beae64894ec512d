"""Webhook delivery as a process: one attempt of one delivery, and the next one scheduled when it must be retried.

`deliver` is what the delivery job runs (workers.webhooks.deliver_webhook is its RQ adapter). An attempt is
claimed in SQL (so a job queued twice sends once), signed afresh (its `webhook-timestamp` is the time of sending;
`webhook-id` is the event's, the same for every retry and redelivery), sent with no redirects and through the
SSRF policy, then recorded; a retry is queued at its time after that commit. If the queue is unreachable for
that, the delivery stays pending in SQL and the sweep (or a worker starting) queues it again. A delivery or
subscription deleted meanwhile ends the attempt quietly.
"""

from __future__ import annotations

import logging
import time
import uuid
from datetime import timedelta

from service.dispatch import UNAVAILABLE_ERRORS, Dispatcher
from service.observability.logs import WEBHOOK_JOBS_LOGGER
from service.observability.metrics import WebhookOutcome, record_webhook_delivery
from service.settings import Settings
from service.store.models import utc_now
from service.store.sessions import transaction

from .delivery import decide_attempt, send, utc_timestamp_s
from .repository import (
    AttemptRecord,
    Claim,
    Leased,
    claim_attempt,
    prune_webhook_log,
    record_attempt,
)
from .signing import signed_headers

log = logging.getLogger(WEBHOOK_JOBS_LOGGER)

# RQ schedules jobs to the whole second, so an attempt queued for the moment its predecessor's lease runs out (a
# worker killed in the middle of an attempt; the start-up pass queues the next one then) may start up to a second
# early. It waits that lease out instead of finding the delivery taken and leaving it to the periodic sweep, which
# comes a minute and more later. How long is left is judged on the claim's own clock (`Leased`): read again
# afterwards, a lease ending in between looked over and the attempt went to the sweep (a fault test, once).
SCHEDULE_SLACK_S = 2.0
# Each worker process prunes the delivery log at most this often (one DELETE, after a delivery).
PRUNE_INTERVAL_S = 3600.0
# The delivery-metric label of each decision; an attempt the SSRF policy refused counts as `blocked`.
_METRIC_OUTCOMES: dict[str, WebhookOutcome] = {"delivered": "delivered", "retry": "retrying", "failed": "failed"}
_last_prune_s = -PRUNE_INTERVAL_S


def deliver(settings: Settings, dispatcher: Dispatcher, delivery_id: uuid.UUID, attempt: int) -> str:
    """Make attempt number `attempt` of a delivery; returns delivered, retry, failed, or why nothing was sent
    (gone, skipped, paused)."""
    claim = _claim(settings, delivery_id, attempt)
    if isinstance(claim, Leased) and claim.left_s <= SCHEDULE_SLACK_S:
        time.sleep(claim.left_s + 0.05)
        claim = _claim(settings, delivery_id, attempt)
    if isinstance(claim, Leased):
        return "skipped"
    if isinstance(claim, str):
        return claim
    record = _attempt(claim, settings)
    with transaction(settings) as session:
        recorded = record_attempt(session, delivery_id, attempt, record)
    if not recorded:
        return "gone"  # the subscription was deleted while the request was out
    outcome, reason = record.decision.outcome, record.decision.reason
    log.info("webhook delivery %s attempt %d: %s (%s)", delivery_id, attempt, outcome, reason or "ok")
    if outcome == "retry":
        try:
            dispatcher.deliveries_due([(delivery_id, attempt + 1, record.next_attempt_at)])
        except UNAVAILABLE_ERRORS as exc:
            log.warning("could not queue retry %d of delivery %s (the sweep will): %s", attempt + 1, delivery_id, exc)
    _prune_now_and_then(settings)
    return outcome


def _claim(settings: Settings, delivery_id: uuid.UUID, attempt: int) -> Claim | Leased | str:
    lease_s = 3 * settings.webhook_timeout_s + settings.webhook_lease_margin_s
    with transaction(settings) as session:
        return claim_attempt(session, delivery_id, attempt, lease_s=lease_s)


def _attempt(claim: Claim, settings: Settings) -> AttemptRecord:
    """Sign, send, and decide: what the attempt's row and its delivery will say."""
    headers = signed_headers(claim.secrets, claim.message_id, utc_timestamp_s(), claim.body)
    result = send(
        claim.url,
        claim.body,
        headers,
        timeout_s=settings.webhook_timeout_s,
        allowed=settings.webhook_allowed_networks,
    )
    decision = decide_attempt(
        result,
        claim.attempt,
        max_attempts=settings.webhook_max_attempts,
        base_s=settings.webhook_retry_base_s,
        cap_s=settings.webhook_retry_cap_s,
    )
    record_webhook_delivery(_METRIC_OUTCOMES[decision.outcome] if not result.refused else "blocked")
    next_attempt_at = None if decision.delay_s is None else utc_now() + timedelta(seconds=decision.delay_s)
    return AttemptRecord(result, decision, next_attempt_at)


def _prune_now_and_then(settings: Settings) -> None:
    global _last_prune_s
    if time.monotonic() - _last_prune_s < PRUNE_INTERVAL_S:
        return
    _last_prune_s = time.monotonic()
    before = utc_now() - timedelta(days=settings.webhook_log_retention_days)
    with transaction(settings) as session:
        pruned = prune_webhook_log(session, before=before)
    if pruned:
        log.info("pruned %d webhook events older than %s from the delivery log", pruned, before.isoformat())
