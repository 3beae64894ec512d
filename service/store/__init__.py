"""The SQL store every room shares: the schema (models, webhook_models), engines and sessions (db; sessions for
jobs and commands), and migrations (migrate; the scripts are in migrations/).

Each room keeps its own operations in its `repository` module (service.cameras.repository, ...). This package
re-exports the pieces most callers need to open a database.
"""

from .db import make_engine, make_session_factory, normalise_url
from .models import (
    ApiKey,
    Base,
    CalibrationVersion,
    Camera,
    Frame,
    FrameImage,
    Observation,
    StaticSpot,
    ViolationEvent,
)
from .webhook_models import ViolationCooldown, WebhookAttempt, WebhookDelivery, WebhookEvent, WebhookSubscription

__all__ = [
    "ApiKey",
    "Base",
    "CalibrationVersion",
    "Camera",
    "Frame",
    "FrameImage",
    "Observation",
    "StaticSpot",
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
