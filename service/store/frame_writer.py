"""Group commit for posted keypoint frames: the frames that arrive while one batch is written go in the next.

Under load most of the cost of storing a frame is the transaction around it (BEGIN, three statements through
SQLAlchemy, COMMIT), not its rows. Request threads therefore hand their frame to a `FrameWriter` and wait: the
first thread to find the writer free becomes the leader and stores every frame waiting at that moment in one
transaction (`repository.add_keypoint_frames`), then wakes their threads. Nobody waits for a timer: an idle API
writes each frame alone, at once, and batches form only from frames that would have queued for the database's
write lock anyway. The same holds on PostgreSQL, where a batch is also one round trip per table.

Each frame still gets its own answer. When a batch fails as a whole because of one frame (its camera deleted
meanwhile, or its client frame id stored by another process since the check), the leader stores that batch's
frames one at a time with `add_keypoint_frame`, which answers each of them as a single post would. Any other
failure (the database unreachable) is every waiting frame's failure: none of them was stored.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from .models import Frame
from .repository import NewKeypointFrame, add_keypoint_frame, add_keypoint_frames

# Most frames one transaction stores: enough to absorb every request thread of an API process, few enough that
# the write lock is held for milliseconds.
MAX_BATCH_FRAMES = 64


@dataclass
class _Waiting:
    frame: NewKeypointFrame
    done: threading.Event = field(default_factory=threading.Event)
    stored: tuple[Frame, bool] | None = None
    error: BaseException | None = None


class FrameWriter:
    """Stores keypoint frames for many threads at once; `add` blocks until its frame is committed (or failed)."""

    def __init__(self, session_factory: sessionmaker[Session], *, max_batch: int = MAX_BATCH_FRAMES) -> None:
        self.session_factory = session_factory
        self.max_batch = max_batch
        self._waiting: deque[_Waiting] = deque()
        self._leader = threading.Lock()

    def add(self, frame: NewKeypointFrame) -> tuple[Frame, bool]:
        """Store one frame; returns (frame, created) as `repository.add_keypoint_frame` does, or raises its error."""
        waiting = _Waiting(frame)
        self._waiting.append(waiting)
        while not waiting.done.is_set():
            with self._leader:
                # A previous leader may have stored this frame while we waited for the lock; a frame still
                # waiting here is in the queue (leaders finish every frame they take before releasing).
                if not waiting.done.is_set():
                    self._write(self._take())
        if waiting.error is not None:
            raise waiting.error
        assert waiting.stored is not None
        return waiting.stored

    def _take(self) -> list[_Waiting]:
        batch: list[_Waiting] = []
        while self._waiting and len(batch) < self.max_batch:
            batch.append(self._waiting.popleft())
        return batch

    def _write(self, batch: list[_Waiting]) -> None:
        """Answer every frame of the batch, whatever happens: a waiting thread must never wait for ever."""
        try:
            answers = self.store_batch([waiting.frame for waiting in batch])
            for waiting, answer in zip(batch, answers, strict=True):
                if isinstance(answer, Exception):
                    waiting.error = answer
                else:
                    waiting.stored = answer
        except BaseException as exc:
            for waiting in batch:
                waiting.error = exc
            if not isinstance(exc, Exception):
                raise
        finally:
            for waiting in batch:
                waiting.done.set()

    def store_batch(self, frames: list[NewKeypointFrame]) -> list[tuple[Frame, bool] | Exception]:
        """Store frames in one transaction, or one at a time if one of them spoils the batch; one answer each.

        Raises only what fails every frame alike (the database unreachable).
        """
        try:
            with self.session_factory() as session:
                stored = add_keypoint_frames(session, frames)
                session.commit()
            return list(stored)
        except IntegrityError:
            return [self._store_alone(frame) for frame in frames]

    def _store_alone(self, frame: NewKeypointFrame) -> tuple[Frame, bool] | Exception:
        try:
            with self.session_factory() as session:
                stored = add_keypoint_frame(
                    session,
                    frame.camera.id,
                    timestamp=frame.timestamp,
                    people=frame.people,
                    client_frame_id=frame.client_frame_id,
                    camera=frame.camera,
                )
                session.commit()
            return stored
        except Exception as exc:
            return exc
