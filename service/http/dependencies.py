"""What every room's routes take: the per-request session, the settings and dispatcher, the camera id path, and
the answers for work that needs the queue."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from typing import Annotated, Any

import anyio
import anyio.to_thread
from fastapi import Depends, Path, Request
from sqlalchemy.orm import Session

from service.dispatch import UNAVAILABLE_ERRORS, Dispatcher
from service.http.problems import UNAVAILABLE_HEADERS, ProblemError
from service.http.schemas import CAMERA_ID_PATTERN
from service.settings import Settings

log = logging.getLogger(__name__)

CameraIdPath = Annotated[
    str,
    Path(
        pattern=CAMERA_ID_PATTERN,
        description="The camera's id: 1-64 characters, letters, digits, '.', '_' and '-', starting with a "
        "letter or digit.",
        examples=["lobby-1"],
    ),
]


async def get_session(request: Request) -> AsyncIterator[Session]:
    """One session per request; the handler commits its unit of work, anything uncommitted is rolled back.

    Made on the event loop: a session connects only when it runs a statement (in the handler's worker thread), so
    making it needs no trip to a worker thread of its own. Under `posemetry bench load` those trips (one to enter,
    one to leave, besides the handler's) were ~4 % of the API's interpreter time in waking worker threads alone.
    Closing hands the connection back: a local call on SQLite, made here; a round trip on PostgreSQL, which goes to a
    worker thread so that the event loop never waits on the network."""
    session = request.app.state.session_factory()
    try:
        yield session
    finally:
        await _close(session)


async def get_read_session(request: Request) -> AsyncIterator[Session]:
    """A session for routes that only read: on SQLite it never waits for (or holds) the write lock. Made and closed
    as `get_session`'s."""
    session = request.app.state.read_session_factory()
    try:
        yield session
    finally:
        await _close(session)


async def _close(session: Session) -> None:
    if session.get_bind().dialect.name == "sqlite":
        session.close()
        return
    # As FastAPI closes its own thread-run dependencies: shielded (a cancelled request still hands its connection
    # back) and outside the request threads' limit (requests waiting in every worker thread for a pooled connection
    # must not keep the close that frees one from running).
    with anyio.CancelScope(shield=True):
        await anyio.to_thread.run_sync(session.close, limiter=anyio.CapacityLimiter(1))


def get_settings(request: Request) -> Settings:
    return request.app.state.settings  # type: ignore[no-any-return]


def get_dispatcher(request: Request) -> Dispatcher:
    return request.app.state.dispatcher  # type: ignore[no-any-return]


SessionDep = Annotated[Session, Depends(get_session)]
ReadSessionDep = Annotated[Session, Depends(get_read_session)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
DispatcherDep = Annotated[Dispatcher, Depends(get_dispatcher)]


def queue_unavailable(action: str, exc: BaseException, **extensions: Any) -> ProblemError:
    """503 for work that needs the queue; what the request stored stays stored."""
    detail = f"The work queue is unreachable ({exc}); {action}"
    return ProblemError(503, "queue-unavailable", detail, headers=UNAVAILABLE_HEADERS, **extensions)


def nudge_best_effort(action: str, call: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
    """A nudge whose loss is harmless (the next frame nudges again): logged, never an error for the client."""
    try:
        call(*args, **kwargs)
    except UNAVAILABLE_ERRORS as exc:
        log.warning("could not %s: %s", action, exc)
