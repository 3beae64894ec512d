"""Signed webhooks (Standard Webhooks): what is sent (payloads, events), how it is signed (signing), where it may
go (addresses), how an attempt is made and judged (delivery), and which violations are worth an alert (cooldown).

The delivery job itself lives in `workers.webhooks`; the API's routes in `service.routers.webhooks`.
"""
