"""The SQL store: schema (models), engines and sessions (db), operations (repository), migrations (migrate).

Import the repository functions from `service.store.repository`; this package re-exports the pieces most
callers need to open a database.
"""

from .db import make_engine, make_session_factory, normalise_url
from .models import ApiKey, Base, CalibrationVersion, Camera, Frame, FrameImage, Observation, ViolationEvent
from .webhook_models import ViolationCooldown, WebhookAttempt, WebhookDelivery, WebhookEvent, WebhookSubscription

__all__ = [
    "ApiKey",
    "Base",
    "CalibrationVersion",
    "Camera",
    "Frame",
    "FrameImage",
    "Observation",
    "ViolationCooldown",
    "ViolationEvent",
    "WebhookAttempt",
    "WebhookDelivery",
    "WebhookEvent",
    "WebhookSubscription",
    "make_engine",
    "make_session_factory",
    "normalise_url",
]
