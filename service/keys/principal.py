"""Who is calling: the key a request was authenticated with, reduced to what authorisation needs."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

# The name the configured admin key (setting POSEMETRY_ADMIN_KEY) goes by; it has no stored row and no id.
SETTINGS_ADMIN_NAME = "POSEMETRY_ADMIN_KEY"


@dataclass(frozen=True)
class Principal:
    """An authenticated caller.

    `cameras` is None for a key that may use every camera, else the camera ids it is limited to (they need not
    exist yet: a scoped key may create its own cameras with PUT). Admin keys are never camera-scoped.
    """

    key_id: str | None
    """The stored key's id; None for the admin key configured in the settings."""
    name: str
    admin: bool
    cameras: frozenset[str] | None = None
    expires_at: datetime | None = None

    def can_access(self, camera_id: str) -> bool:
        return self.cameras is None or camera_id in self.cameras


SETTINGS_ADMIN = Principal(key_id=None, name=SETTINGS_ADMIN_NAME, admin=True)
