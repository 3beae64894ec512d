"""Synchronous measurement: people in, distances out, with the camera's current calibration (nothing stored)."""

from __future__ import annotations

from fastapi import APIRouter

from service.calibration.repository import current_calibration
from service.cameras.service import require_camera
from service.distances.schemas import DistanceRequest
from service.frames.schemas import FrameResult
from service.frames.service import compute_frame_result, people_for_camera
from service.http.dependencies import CameraIdPath, ReadSessionDep, SettingsDep
from service.http.links import camera_url
from service.http.problems import ProblemError

router = APIRouter(prefix="/v1/cameras", tags=["distances"])


@router.post("/{camera_id}/distances", response_model=FrameResult)
def post_distances(
    camera_id: CameraIdPath, body: DistanceRequest, session: ReadSessionDep, settings: SettingsDep
) -> FrameResult:
    """Positions, every pair's distance with its 1-sigma, and violations; 409 while the camera is uncalibrated."""
    camera = require_camera(session, camera_id)
    people = people_for_camera(body.people, camera, settings)
    calibration = current_calibration(session, camera_id)
    image_size_px = (camera.image_width_px, camera.image_height_px)
    threshold_m = camera.distance_threshold_m
    if calibration is not None:
        session.expunge(calibration)  # keep its loaded values readable after the rollback below
    session.rollback()  # measuring needs no transaction; end the read snapshot before computing
    if calibration is None:
        raise ProblemError(
            409,
            "camera-uncalibrated",
            f"Camera {camera_id!r} has no calibration yet; see GET {camera_url(camera_id)}/calibration for how "
            "much more evidence it needs.",
        )
    return compute_frame_result(
        people, calibration, image_size_px=image_size_px, distance_threshold_m=threshold_m
    ).result
