"""The URLs the API's answers link to, in one place (the routes are mounted under these paths)."""

from __future__ import annotations

import uuid


def camera_url(camera_id: str) -> str:
    return f"/v1/cameras/{camera_id}"


def frame_url(camera_id: str, frame_id: uuid.UUID) -> str:
    return f"{camera_url(camera_id)}/frames/{frame_id}"
