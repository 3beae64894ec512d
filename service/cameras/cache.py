"""The cameras the keypoint hot path has read recently, per API process.

Accepting a keypoint frame needs its camera's id and image size. Reading them costs a session, a pooled
connection and a query: a third of the API's CPU per frame. Cameras change rarely, so each API process keeps what
it read for `ttl_s` and forgets a camera at once when it changes or deletes it itself.

An entry past `ttl_s` is still served, for up to another `ttl_s`, while one background thread reads the camera
again: no request waits for the database because a camera's time ran out. (Reading on the request's behalf,
through the thread pool, cost 25 requests a second at 50 cameras and a 2 s ttl; queued behind the GIL, they were
the 99th percentile of ingest latency.) An entry past twice `ttl_s` (its refresh failed) is read by the request.

What another process changed is seen here within about `ttl_s`, twice that at worst, but no frame depends on it:
the store reads the camera's image size again in the transaction that stores the frame (a row that transaction
locks and updates anyway), and refuses a frame checked against another size; the API then forgets the entry,
reads the camera and checks the frame against the new size. So a resize binds every process's next frame, and
a deleted camera is a 404 at once. A camera that does not exist is never remembered, so one created elsewhere is
found at once.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from sqlalchemy.orm import Session

from service.cameras.repository import get_camera
from service.store.models import Camera

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Entry:
    camera: Camera
    """Detached from its session; only loaded columns are read (id and image size)."""
    expires_at: float


class CameraCache:
    def __init__(
        self, ttl_s: float, sessions: Callable[[], Session], clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.ttl_s = ttl_s
        self._sessions = sessions
        self._clock = clock
        self._entries: dict[str, _Entry] = {}
        self._lock = threading.Lock()
        self._refreshing: set[str] = set()
        self._forgets = 0  # bumped by forget(): a read that began before it must not store what it read
        self._closed = False
        self._refresher = ThreadPoolExecutor(max_workers=1, thread_name_prefix="camera-cache")

    def cached(self, camera_id: str) -> Camera | None:
        """The camera if memory holds it, without reading (safe on the event loop); None if the caller must read.

        A stale entry is returned as it is and refreshed in the background."""
        entry = self._entries.get(camera_id)
        if entry is None:
            return None
        now = self._clock()
        if now < entry.expires_at:
            return entry.camera
        if now < entry.expires_at + self.ttl_s and self._refresh_later(camera_id):
            return entry.camera
        return None

    def get(self, camera_id: str) -> Camera | None:
        """The camera, from memory if there, else read now (blocking); None if it does not exist."""
        camera = self.cached(camera_id)
        return camera if camera is not None else self._read(camera_id)

    def forget(self, camera_id: str) -> None:
        """Called by this process after it changed or deleted the camera."""
        with self._lock:
            self._forgets += 1
            self._entries.pop(camera_id, None)

    def close(self) -> None:
        """Stop refreshing (waiting for a refresh under way); `get` still reads."""
        with self._lock:
            self._closed = True
        self._refresher.shutdown(wait=True)

    def _read(self, camera_id: str) -> Camera | None:
        now, forgets = self._clock(), self._forgets
        with self._sessions() as session:
            camera = get_camera(session, camera_id)
        with self._lock:
            if camera is None:
                self._entries.pop(camera_id, None)
            elif self.ttl_s > 0 and forgets == self._forgets:
                self._entries[camera_id] = _Entry(camera, now + self.ttl_s)
        return camera

    def _refresh_later(self, camera_id: str) -> bool:
        """Have the camera read again in the background (once, however many requests find it stale); False
        once closed."""
        with self._lock:
            if self._closed:
                return False
            if camera_id not in self._refreshing:
                self._refreshing.add(camera_id)
                self._refresher.submit(self._refresh, camera_id)
        return True

    def _refresh(self, camera_id: str) -> None:
        try:
            self._read(camera_id)
        except Exception as exc:  # the database unreachable: requests read it themselves once the entry is too old
            log.debug("could not refresh camera %s: %s", camera_id, exc)
        finally:
            with self._lock:
                self._refreshing.discard(camera_id)
