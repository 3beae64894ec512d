"""Dependencies and checks shared by the routers: the per-request session, settings, dispatcher and camera."""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from typing import Annotated, Any

from fastapi import Depends, Path, Request
from sqlalchemy.orm import Session

from service.dispatch import UNAVAILABLE_ERRORS, Dispatcher
from service.keypoints import person_from_centres, person_from_keypoints
from service.problems import UNAVAILABLE_HEADERS, ProblemError, field_errors
from service.schemas import CAMERA_ID_PATTERN, PersonObservation
from service.settings import Settings
from service.store import repository
from service.store.models import Camera
from service.store.repository import PersonIn

# Keypoints may lie somewhat outside the image (pose models extrapolate cut-off limbs), but not absurdly far:
# anything beyond half an image width/height past an edge is a unit or coordinate-system mistake.
COORDINATE_MARGIN_FRACTION = 0.5
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


def camera_url(camera_id: str) -> str:
    return f"/v1/cameras/{camera_id}"


def camera_not_found(camera_id: str) -> ProblemError:
    return ProblemError(
        404, "camera-not-found", f"No camera {camera_id!r}: create it with PUT {camera_url(camera_id)}."
    )


def require_camera(session: Session, camera_id: str) -> Camera:
    camera = repository.get_camera(session, camera_id)
    if camera is None:
        raise camera_not_found(camera_id)
    return camera


def queue_unavailable(action: str, exc: BaseException, **extensions: Any) -> ProblemError:
    """503 for work that needs the queue; what the request stored stays stored."""
    detail = f"The work queue is unreachable ({exc}); {action}"
    return ProblemError(503, "queue-unavailable", detail, headers=UNAVAILABLE_HEADERS, **extensions)


def nudge_best_effort(action: str, call: Any, *args: Any, **kwargs: Any) -> None:
    """A nudge whose loss is harmless (the next frame nudges again): logged, never an error for the client."""
    try:
        call(*args, **kwargs)
    except UNAVAILABLE_ERRORS as exc:
        log.warning("could not %s: %s", action, exc)


def people_for_camera(people: Sequence[PersonObservation], camera: Camera, settings: Settings) -> list[PersonIn]:
    """Posted people as store rows, after the checks that need the camera and the settings.

    Too many people is 413 (settings.max_people_per_frame). Coordinates more than half an image beyond an edge
    are 422 with each bad field's location, whatever their score: pose models put the joints they did not find
    at placeholders inside or next to the image (0, 0 or -1, -1), never half an image away, and a number that
    passes here must be one the store can keep (a score-0 keypoint at 1e39 once failed a whole write batch).
    """
    if len(people) > settings.max_people_per_frame:
        raise ProblemError(
            413,
            "too-many-people",
            f"{len(people)} people in one frame; at most {settings.max_people_per_frame} are accepted "
            "(setting max_people_per_frame).",
        )
    width, height = size = (camera.image_width_px, camera.image_height_px)
    # The accepted band per axis. The loops below compare inline: 340 points per frame, where a function call per
    # point was a quarter of the event loop's time per frame.
    low_x, high_x = -COORDINATE_MARGIN_FRACTION * width, (1 + COORDINATE_MARGIN_FRACTION) * width
    low_y, high_y = -COORDINATE_MARGIN_FRACTION * height, (1 + COORDINATE_MARGIN_FRACTION) * height
    errors: list[dict[str, Any]] = []

    def far_outside(loc: list[Any], x: float, y: float) -> None:
        errors.append(
            {
                "loc": ["body", "people", *loc],
                "msg": f"point ({x:g}, {y:g}) px is far outside the camera's {width}x{height} image",
                "type": "coordinate_out_of_image",
            }
        )

    rows = []
    for index, person in enumerate(people):
        if person.keypoints is not None:
            for k, (x, y, _score) in enumerate(person.keypoints):
                if not (low_x <= x <= high_x and low_y <= y <= high_y):
                    far_outside([index, "keypoints", k], x, y)
            rows.append(person_from_keypoints(person.keypoints, size))
        else:
            for name in ("shoulder", "ankle"):
                point = getattr(person, name)
                if point is not None and not (low_x <= point[0] <= high_x and low_y <= point[1] <= high_y):
                    far_outside([index, name], *point)
            rows.append(person_from_centres(person.shoulder, person.ankle, size))
    if errors:
        fields = field_errors(errors)
        more = f" (and {len(fields) - 1} more)" if len(fields) > 1 else ""
        detail = f"Invalid request: {fields[0]['field']}: {fields[0]['msg']}{more}"
        raise ProblemError(422, "validation-error", detail, errors=fields)
    return rows
