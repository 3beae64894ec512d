"""How the API hands work to the workers, behind a small protocol so the API never imports the queue.

The API stores first and dispatches second: a frame is in SQL before any worker hears of it, so losing the
queue loses no data (workers re-enqueue pending frames on start). The Redis implementation is service.queue
(the API gets one from `posemetry api`/`serve`, never by importing it); this module holds the protocol, the error
the API turns into 503, and the dispatcher that does nothing, for queue-less runs. (The tests' recording one is
tests.support.dispatch.)
"""

from __future__ import annotations

import uuid
from collections.abc import Iterable, Sequence
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
