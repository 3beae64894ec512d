"""How the API hands work to the workers, behind a small protocol so the API never imports the queue.

The API stores first and dispatches second: a frame is in SQL before any worker hears of it, so losing the
queue loses no data (workers re-enqueue pending frames on start). The Redis implementation lives with the
workers; this module holds the protocol, the error the API turns into 503, and two in-process implementations
(one that does nothing, one that records calls and can be told to fail) for tests and queue-less runs.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Protocol, runtime_checkable


class DispatchUnavailableError(ConnectionError):
    """The queue cannot be reached. Implementations raise this (or any ConnectionError/TimeoutError); the API
    answers 503 and keeps what it already stored."""


@runtime_checkable
class Dispatcher(Protocol):
    """Nudges for the workers. Every method must be cheap and idempotent: the API may call them again for the
    same frame or camera (client retries, a reset), and the implementation deduplicates."""

    def frames_stored(self, frames: Sequence[tuple[str, uuid.UUID]]) -> None:
        """Frames (camera id, frame id) and their people are committed; measure them (now, or once their camera is
        calibrated). The API calls this once per write batch, so it must cost one round trip, not one per frame."""

    def image_stored(self, camera_id: str, frame_id: uuid.UUID) -> None:
        """An image frame is committed; find its people (pose), then measure it."""

    def calibration_requested(self, camera_id: str, forced: bool) -> None:
        """Solve the camera's calibration: because evidence grew (forced=False) or on demand (forced=True,
        the new version becomes current even if less well supported)."""

    def deliveries_due(self, due: Iterable[tuple[uuid.UUID, int, datetime | None]]) -> int:
        """Webhook deliveries are committed (pending): make attempt number n of each, at its time (None: now).
        Returns how many attempts were queued (one already waiting is not queued again)."""

    def ready(self) -> bool:
        """Whether work can be queued now (for /readyz); may raise DispatchUnavailableError instead of False."""


UNAVAILABLE_ERRORS: tuple[type[BaseException], ...] = (DispatchUnavailableError, ConnectionError, TimeoutError)


class NullDispatcher:
    """Accepts everything and does nothing: for an API run without workers (frames then stay pending)."""

    def frames_stored(self, frames: Sequence[tuple[str, uuid.UUID]]) -> None:
        return None

    def image_stored(self, camera_id: str, frame_id: uuid.UUID) -> None:
        return None

    def calibration_requested(self, camera_id: str, forced: bool) -> None:
        return None

    def deliveries_due(self, due: Iterable[tuple[uuid.UUID, int, datetime | None]]) -> int:
        return 0

    def ready(self) -> bool:
        return True


@dataclass
class RecordingDispatcher:
    """Records every call in order; set `fail` to make calls raise DispatchUnavailableError (queue down)."""

    fail: bool = False
    frames: list[tuple[str, uuid.UUID]] = field(default_factory=list)
    images: list[tuple[str, uuid.UUID]] = field(default_factory=list)
    calibrations: list[tuple[str, bool]] = field(default_factory=list)
    deliveries: list[tuple[uuid.UUID, int, datetime | None]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def _check(self) -> None:
        if self.fail:
            raise DispatchUnavailableError("queue unreachable (RecordingDispatcher.fail is set)")

    def frames_stored(self, frames: Sequence[tuple[str, uuid.UUID]]) -> None:
        self._check()
        with self._lock:
            self.frames.extend(frames)

    def image_stored(self, camera_id: str, frame_id: uuid.UUID) -> None:
        self._check()
        with self._lock:
            self.images.append((camera_id, frame_id))

    def calibration_requested(self, camera_id: str, forced: bool) -> None:
        self._check()
        with self._lock:
            self.calibrations.append((camera_id, forced))

    def deliveries_due(self, due: Iterable[tuple[uuid.UUID, int, datetime | None]]) -> int:
        self._check()
        items = list(due)
        with self._lock:
            self.deliveries.extend(items)
        return len(items)

    def ready(self) -> bool:
        self._check()
        return True
