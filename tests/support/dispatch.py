"""A dispatcher that records what the API asks of the workers, and can be told the queue is down.

The API's tests run without Redis and workers: they check what the API would have queued (and that a queue
outage is a 503 that keeps what was stored), while tests/workers and the end-to-end tests run the real queue.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime

from service.dispatch import DispatchUnavailableError


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
