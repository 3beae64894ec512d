"""The cameras the keypoint hot path has read recently, per API process.

Accepting a keypoint frame needs its camera's id and image size. Reading them costs a session, a pooled
connection and a query: a third of the API's CPU per frame. Cameras change rarely, so each API process keeps what
it read for `ttl_s` and forgets a camera at once when it changes or deletes it itself.

What another process changed is seen within `ttl_s`: a camera deleted there meanwhile still fails the frame's
insert (its foreign key) and is answered 404; a new image size set there applies to this process's frames after
at most `ttl_s`. A camera that does not exist is never remembered, so one created elsewhere is found at once.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy.orm import Session

from service.store.models import Camera
from service.store.repository import get_camera


@dataclass(frozen=True)
class _Entry:
    camera: Camera
    """Detached from its session; only loaded columns are read (id and image size)."""
    expires_at: float


class CameraCache:
    def __init__(self, ttl_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.ttl_s = ttl_s
        self._clock = clock
        self._entries: dict[str, _Entry] = {}

    def cached(self, camera_id: str) -> Camera | None:
        """The camera if memory holds it fresh, else None (without reading: safe on the event loop)."""
        entry = self._entries.get(camera_id)
        if entry is not None and self._clock() < entry.expires_at:
            return entry.camera
        return None

    def get(self, sessions: Callable[[], Session], camera_id: str) -> Camera | None:
        """The camera, from memory while fresh, else read with a session from `sessions`; None if it does not
        exist."""
        camera = self.cached(camera_id)
        if camera is not None:
            return camera
        now = self._clock()
        with sessions() as session:
            camera = get_camera(session, camera_id)
        if camera is None:
            self._entries.pop(camera_id, None)
        elif self.ttl_s > 0:
            self._entries[camera_id] = _Entry(camera, now + self.ttl_s)
        return camera

    def forget(self, camera_id: str) -> None:
        """Called by this process after it changed or deleted the camera."""
        self._entries.pop(camera_id, None)
