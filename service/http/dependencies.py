"""What every room's routes take: the per-request session, the settings and dispatcher, the camera id path, and
the answers for work that needs the queue."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from typing import Annotated, Any

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


def get_session(request: Request) -> Iterator[Session]:
    """One session per request; the handler commits its unit of work, anything uncommitted is rolled back."""
    with request.app.state.session_factory() as session:
        yield session


def get_read_session(request: Request) -> Iterator[Session]:
    """A session for routes that only read: on SQLite it never waits for (or holds) the write lock."""
    with request.app.state.read_session_factory() as session:
        yield session


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
