"""Group commit for posted keypoint frames, on one writer thread per API process.

Under load most of the cost of storing a frame is the transaction around it (BEGIN, three statements through
SQLAlchemy, COMMIT), not its rows. Requests therefore hand their frame to the `FrameWriter` (`submit`, which
returns a future the event loop awaits) and the writer thread stores every frame waiting at that moment in one
transaction (`ingest.add_keypoint_frames`), then answers each future. Nobody waits for a timer: an idle writer
stores a frame alone, at once, and batches form only from frames that would have queued for the database's write
lock anyway. The same holds on PostgreSQL, where a batch is also one round trip per table.

One thread, rather than a leader elected among request threads, because every hand-over between threads costs a
wake-up and a wait for the GIL: a request crosses threads to the writer and back, not through the thread pool as
well. `after_commit` runs once per batch on a second thread (the API asks for the batch's cameras to be measured
there), so the writer stores the next batch meanwhile; it may give each frame an error of its own.

Each frame gets its own answer, and one client's frame never costs another client anything. Frames whose camera
was deleted or resized since it was read are named by the store before it writes (FramesRefusedError): they get
their own error and the batch is stored without them. When a batch fails as a whole for any other reason but the
database being unavailable (a client frame id stored by another process since the check, or a frame the store
cannot take), the writer stores that batch's frames one at a time with `add_keypoint_frame`, which answers each of
them as a single post would; a frame that fails alone gets FrameNotStorableError (the API answers 422), never a
500 for its neighbours. A database that is unavailable is every waiting frame's failure (503): none was stored.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import cast

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from service.cameras.repository import CameraNotFoundError, CameraResizedError
from service.domain import CameraCounters
from service.frames.ingest import (
    FramesRefusedError,
    NewKeypointFrame,
    PreparedKeypointFrame,
    add_keypoint_frame,
    add_keypoint_frames,
    prepare_keypoint_frame,
)
from service.store.db import is_database_unavailable
from service.store.models import Frame, utc_now

log = logging.getLogger(__name__)

# Most frames one transaction stores: enough to absorb a burst of requests, few enough that the write lock is
# held for milliseconds.
MAX_BATCH_FRAMES = 64


class FrameNotStorableError(ValueError):
    """A frame the store refused on its own (not its camera, not the database): the API answers 422. Validation
    should have refused it first; each one is logged as an error, because it names a gap in that validation."""


# Errors a frame gets as they are: the API has an answer for each.
_OWN_ERRORS = (CameraNotFoundError, CameraResizedError)


def _unavailable(exc: BaseException) -> bool:
    return isinstance(exc, SQLAlchemyError) and is_database_unavailable(exc)


@dataclass(frozen=True)
class StoredFrame:
    """A frame's answer: the stored frame, whether this post created it, and what `after_commit` said of it."""

    frame: Frame
    created: bool
    after_commit_error: BaseException | None = None


AfterCommit = Callable[[Sequence[tuple[Frame, bool]], Mapping[str, CameraCounters]], Sequence[BaseException | None]]
"""Called with a batch's stored frames and the evidence counters its transaction left on the cameras whose people it
stored (ingest.add_keypoint_frames; frames stored one at a time leave none), after its commit; returns one error (or
None) per frame."""


class FrameWriter:
    """Stores keypoint frames submitted from any thread, a batch per transaction, on its own thread."""

    def __init__(
        self,
        session_factory: sessionmaker[Session],
        *,
        max_batch: int = MAX_BATCH_FRAMES,
        after_commit: AfterCommit | None = None,
    ) -> None:
        self.session_factory = session_factory
        self.max_batch = max_batch
        self.after_commit = after_commit
        self._waiting: deque[tuple[NewKeypointFrame, Future[StoredFrame]]] = deque()
        self._wakeup = threading.Condition()
        self._thread: threading.Thread | None = None
        self._closed = False
        # after_commit runs on a thread of its own, so the writer stores the next batch meanwhile.
        self._after = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-after-commit")

    def submit(self, frame: NewKeypointFrame) -> Future[StoredFrame]:
        """Queue one frame; the future holds its StoredFrame, or the error that kept it from the store."""
        future: Future[StoredFrame] = Future()
        with self._wakeup:
            if self._closed:
                raise RuntimeError("the frame writer is closed")
            self._waiting.append((frame, future))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="frame-writer", daemon=True)
                self._thread.start()
            self._wakeup.notify()
        return future

    def add(self, frame: NewKeypointFrame) -> StoredFrame:
        """Store one frame and wait for it (for callers on threads of their own)."""
        return self.submit(frame).result()

    def close(self, timeout_s: float = 30.0) -> None:
        """Refuse new frames, store and answer those already queued, and stop the threads."""
        with self._wakeup:
            self._closed = True
            self._wakeup.notify()
            thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
        self._after.shutdown(wait=True)

    def _run(self) -> None:
        while True:
            with self._wakeup:
                while not self._waiting and not self._closed:
                    self._wakeup.wait()
                if not self._waiting:
                    return  # closed, and every queued frame answered
                batch = self._take()
            if batch:
                self._write(batch)

    def _take(self) -> list[tuple[NewKeypointFrame, Future[StoredFrame]]]:
        batch = []
        while self._waiting and len(batch) < self.max_batch:
            frame, future = self._waiting.popleft()
            # A request cancelled before its frame was taken is not stored (it got no answer; a retry may come).
            if future.set_running_or_notify_cancel():
                batch.append((frame, future))
        return batch

    def _write(self, batch: list[tuple[NewKeypointFrame, Future[StoredFrame]]]) -> None:
        counters: dict[str, CameraCounters] = {}
        try:
            answers = self.store_batch([frame for frame, _ in batch], counters)
        except BaseException as exc:
            _fail(batch, exc)
            if not isinstance(exc, Exception):
                raise
            return
        if self.after_commit is None:
            self._answer(batch, answers, counters)
        else:
            self._after.submit(self._answer, batch, answers, counters)

    def _answer(
        self,
        batch: list[tuple[NewKeypointFrame, Future[StoredFrame]]],
        answers: list[tuple[Frame, bool] | Exception],
        counters: Mapping[str, CameraCounters],
    ) -> None:
        """Answer every frame of the batch, whatever happens: a waiting request must never wait for ever, and the
        threads must outlive any one batch."""
        try:
            stored = [answer for answer in answers if not isinstance(answer, Exception)]
            no_errors: Sequence[BaseException | None] = [None] * len(stored)
            after = self.after_commit
            errors = iter(after(stored, counters) if after is not None and stored else no_errors)
            for (_, future), answer in zip(batch, answers, strict=True):
                if isinstance(answer, Exception):
                    future.set_exception(answer)
                else:
                    future.set_result(StoredFrame(answer[0], answer[1], next(errors)))
        except BaseException as exc:
            _fail(batch, exc)
            if not isinstance(exc, Exception):
                raise

    def store_batch(
        self, frames: list[NewKeypointFrame], counters: dict[str, CameraCounters] | None = None
    ) -> list[tuple[Frame, bool] | Exception]:
        """Store frames in one transaction, without those the store refuses, or one at a time if one of them spoils
        the batch; one answer each (a (frame, created) pair, or that frame's own error). `counters` receives the
        evidence counters the batch's transaction left (add_keypoint_frames).

        Raises only what fails every frame alike (the database unavailable).
        """
        answers: list[tuple[Frame, bool] | Exception | None] = [None] * len(frames)
        # Rows are built before the transaction, which on SQLite holds the one write lock every writer waits for.
        prepared: dict[int, PreparedKeypointFrame] = {}
        received_at = utc_now()
        for i, frame in enumerate(frames):
            try:
                prepared[i] = prepare_keypoint_frame(frame, received_at=received_at)
            except ValueError:
                answers[i] = self._store_alone(frame)  # answers it as a single post would
        waiting = sorted(prepared)
        while waiting:
            try:
                with self.session_factory() as session:
                    stored = add_keypoint_frames(session, [prepared[i] for i in waiting], counters)
                    session.commit()
            except FramesRefusedError as refused:
                for position, error in refused.errors.items():
                    answers[waiting[position]] = error
                waiting = [i for position, i in enumerate(waiting) if position not in refused.errors]
                continue
            except Exception as exc:
                if _unavailable(exc):
                    raise
                if counters is not None:
                    counters.clear()  # read in the transaction that rolled back
                for i in waiting:
                    answers[i] = self._store_alone(frames[i])
                break
            for i, answer in zip(waiting, stored, strict=True):
                answers[i] = answer
            break
        return cast(list[tuple[Frame, bool] | Exception], answers)  # every position answered above

    def _store_alone(self, frame: NewKeypointFrame) -> tuple[Frame, bool] | Exception:
        """One frame in its own transaction; what fails it is its own answer."""
        try:
            with self.session_factory() as session:
                stored = add_keypoint_frame(
                    session,
                    frame.camera.id,
                    timestamp=frame.timestamp,
                    people=frame.people,
                    client_frame_id=frame.client_frame_id,
                    camera=frame.camera,
                    request_id=frame.request_id,
                )
                session.commit()
            return stored
        except _OWN_ERRORS as exc:
            return exc
        except Exception as exc:
            if _unavailable(exc):
                return exc
            log.error("a keypoint frame of camera %s could not be stored: %r", frame.camera.id, exc, exc_info=exc)
            return FrameNotStorableError(f"the frame could not be stored ({type(exc).__name__})")


def _fail(batch: list[tuple[NewKeypointFrame, Future[StoredFrame]]], exc: BaseException) -> None:
    log.debug("a batch of %d keypoint frames failed: %s", len(batch), exc)
    for _, future in batch:
        if not future.done():
            future.set_exception(exc)
