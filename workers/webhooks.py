"""The webhook delivery job: one attempt of one delivery (service.webhooks.service), queued by dotted path."""

from __future__ import annotations

import uuid

from service.settings import get_settings
from service.webhooks.service import deliver
from workers.context import current_dispatcher


def deliver_webhook(delivery_id: str, attempt: int) -> str:
    """Make attempt number `attempt` of a delivery; returns delivered, retry, failed, or why nothing was sent
    (gone, skipped, paused)."""
    settings = get_settings()
    return deliver(settings, current_dispatcher(settings), uuid.UUID(delivery_id), attempt)
