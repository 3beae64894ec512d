"""A frame's pictures: its image with the ground grid and distances drawn on it, and a top-down map."""

from __future__ import annotations

import uuid
from typing import Annotated

from fastapi import APIRouter, Path, Query, Response
from sqlalchemy.orm import Session

from service.calibration.repository import get_calibration
from service.cameras.service import require_camera
from service.frames.repository import frame_image, frame_observations, get_frame
from service.http.dependencies import CameraIdPath, ReadSessionDep
from service.http.links import frame_url
from service.http.problems import ProblemError
from service.pictures.service import StoredFrame, Unit, overlay_png, topdown_png

router = APIRouter(prefix="/v1/cameras", tags=["pictures"])

FrameIdPath = Annotated[uuid.UUID, Path(description="The frame id returned when the frame was posted.")]
UnitQuery = Annotated[Unit, Query(description="Grid cells and labels: `m` (1 m cells) or `ft` (6 ft cells).")]
PNG_RESPONSE = {200: {"content": {"image/png": {}}, "description": "The picture (PNG)"}}


def _stored_frame(session: Session, camera_id: str, frame_id: uuid.UUID) -> StoredFrame:
    camera = require_camera(session, camera_id)
    frame = get_frame(session, camera_id, frame_id)
    if frame is None:
        raise ProblemError(404, "frame-not-found", f"Camera {camera_id!r} has no frame {frame_id}.")
    calibration = None
    if frame.calibration_version is not None:
        calibration = get_calibration(session, camera_id, frame.calibration_version)
    return StoredFrame(frame, camera, frame_observations(session, frame_id), calibration)


@router.get("/{camera_id}/frames/{frame_id}/overlay.png", response_class=Response, responses=PNG_RESPONSE)
def get_overlay(
    camera_id: CameraIdPath, frame_id: FrameIdPath, session: ReadSessionDep, unit: UnitQuery = "m"
) -> Response:
    """The frame's image with the estimated ground grid, each person's box (red when closer than the camera's
    threshold to someone) and a line to their nearest neighbour labelled with the distance.

    Needs the image, which is kept only for cameras with `keep_images`; before the frame is measured the people
    are drawn without distances.
    """
    stored = _stored_frame(session, camera_id, frame_id)
    image = frame_image(session, frame_id)
    if image is None:
        reason = (
            "it was posted as keypoints"
            if stored.frame.source == "keypoints"
            else f"camera {camera_id!r} does not keep images (set keep_images to draw overlays of later frames)"
        )
        raise ProblemError(404, "image-not-kept", f"Frame {frame_id} has no stored image: {reason}.")
    data = image.data
    session.rollback()
    return Response(overlay_png(stored, data, unit=unit), media_type="image/png")


@router.get("/{camera_id}/frames/{frame_id}/topdown.png", response_class=Response, responses=PNG_RESPONSE)
def get_topdown(
    camera_id: CameraIdPath,
    frame_id: FrameIdPath,
    session: ReadSessionDep,
    unit: UnitQuery = "m",
    size_px: Annotated[int, Query(ge=200, le=2000, description="Side of the map in pixels.")] = 800,
) -> Response:
    """A map of where the frame's people stand on the ground, with the camera and its field of view."""
    stored = _stored_frame(session, camera_id, frame_id)
    session.rollback()
    if stored.frame.result is None or stored.calibration is None:
        raise ProblemError(
            409,
            "frame-not-measured",
            f"Frame {frame_id} is {stored.frame.status}, not measured yet; see GET {frame_url(camera_id, frame_id)}.",
        )
    return Response(topdown_png(stored, unit=unit, size_px=size_px), media_type="image/png")
