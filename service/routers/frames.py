"""Keypoint frames in (stored, then dispatched), and their results out."""

from __future__ import annotations

import uuid
from typing import Annotated

from fastapi import APIRouter, Path, Response, status

from service.dispatch import UNAVAILABLE_ERRORS
from service.problems import ProblemError
from service.schemas import FrameAccepted, FrameOut, FrameResult, KeypointFrame
from service.store import repository
from service.store.models import Frame

from .common import (
    CameraIdPath,
    DispatcherDep,
    ReadSessionDep,
    SessionDep,
    SettingsDep,
    camera_not_found,
    camera_url,
    people_for_camera,
    queue_unavailable,
    require_camera,
)

router = APIRouter(prefix="/v1/cameras", tags=["frames"])


def frame_url(camera_id: str, frame_id: uuid.UUID) -> str:
    return f"{camera_url(camera_id)}/frames/{frame_id}"


@router.post(
    "/{camera_id}/keypoints",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=FrameAccepted,
    responses={200: {"description": "A retry of a frame already stored (same client frame_id)"}},
)
def post_keypoints(
    camera_id: CameraIdPath,
    body: KeypointFrame,
    response: Response,
    read_session: ReadSessionDep,
    session: SessionDep,
    settings: SettingsDep,
    dispatcher: DispatcherDep,
) -> FrameAccepted:
    """Store one frame's people, then nudge the workers: 202 with the frame's URL (200 for a retry).

    The measuring worker that picks the frame up also requests a calibration when the camera's evidence calls
    for one, so this hot path makes one call to the queue.

    Posting the same client `frame_id` again returns the stored frame and stores nothing; if that frame is
    still pending it is dispatched again, which is how a client recovers from an earlier 503. When the queue
    is unreachable the answer is 503, but the frame is already committed and workers pick it up on start.
    """
    # Checks and conversion happen before the writing transaction, which on SQLite holds the one write lock.
    camera = require_camera(read_session, camera_id)
    people = people_for_camera(body.people, camera, settings)
    read_session.rollback()
    try:
        frame, created = repository.add_keypoint_frame(
            session,
            camera_id,
            timestamp=body.timestamp,
            people=people,
            client_frame_id=body.frame_id,
            camera=camera,
        )
    except repository.CameraNotFoundError:
        raise camera_not_found(camera_id) from None  # deleted since it was read
    session.commit()
    session.close()  # give the connection back before talking to the queue
    url = frame_url(camera_id, frame.id)
    if created or frame.status == "pending":
        try:
            dispatcher.frame_stored(camera_id, frame.id)
        except UNAVAILABLE_ERRORS as exc:
            raise queue_unavailable(
                "the frame is stored and will be processed when the queue is back.",
                exc,
                frame_id=frame.id,
                url=url,
            ) from exc
    response.status_code = status.HTTP_202_ACCEPTED if created else status.HTTP_200_OK
    response.headers["Location"] = url
    return FrameAccepted(
        frame_id=frame.id,
        client_frame_id=frame.client_frame_id,
        status=frame.status,  # type: ignore[arg-type]
        people=frame.people,
        created=created,
        url=url,
    )


def frame_out(frame: Frame) -> FrameOut:
    return FrameOut(
        frame_id=frame.id,
        camera_id=frame.camera_id,
        client_frame_id=frame.client_frame_id,
        timestamp=frame.timestamp,
        received_at=frame.received_at,
        status=frame.status,  # type: ignore[arg-type]
        people=frame.people,
        calibration_version=frame.calibration_version,
        processed_at=frame.processed_at,
        error=frame.error,
        result=None if frame.result is None else FrameResult.model_validate(frame.result),
    )


@router.get("/{camera_id}/frames/{frame_id}", response_model=FrameOut)
def get_frame(
    camera_id: CameraIdPath,
    frame_id: Annotated[uuid.UUID, Path(description="The frame id returned by the keypoints POST.")],
    session: ReadSessionDep,
) -> FrameOut:
    """A frame's status and, once measured, its people's positions, pair distances and violations."""
    require_camera(session, camera_id)
    frame = repository.get_frame(session, camera_id, frame_id)
    if frame is None:
        raise ProblemError(404, "frame-not-found", f"Camera {camera_id!r} has no frame {frame_id}.")
    return frame_out(frame)
