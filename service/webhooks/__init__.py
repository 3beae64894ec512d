"""Signed webhooks (Standard Webhooks), the whole room: the `/v1/webhooks` routes and their bodies (routes,
schemas), subscriptions, events, deliveries and attempts in the store (repository; the tables are in
service.store.webhook_models), raising events where things happen (events) with their bodies (payloads), how an
attempt is made (service: claim, sign, send, record) and judged (delivery), how it is signed (signing), where it
may go (addresses), and which violations are worth an alert (cooldown).

The delivery job, workers.webhooks.deliver_webhook, is a thin adapter over `service.deliver`.
"""
