"""Cameras: idempotent create/update, list, read, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status

from service.calibration.camera_model import known_focal, principal_point
from service.cameras import repository
from service.cameras.schemas import (
    DEFAULT_CAMERA_HEIGHT_TOLERANCE_M,
    CameraList,
    CameraOut,
    CameraSettings,
    Distortion,
    StaticSpotList,
    StaticSpotOut,
)
from service.cameras.service import apply_settings, require_camera
from service.cameras.static_spots import static_spots
from service.domain import CONVERTED_DECIMALS, metres_to_feet
from service.http.dependencies import (
    CameraIdPath,
    DispatcherDep,
    ReadSessionDep,
    SessionDep,
    SettingsDep,
    nudge_best_effort,
)
from service.http.links import camera_url
from service.keys.dependencies import PrincipalDep
from service.store.models import Camera
from service.webhooks.events import announce

router = APIRouter(prefix="/v1/cameras", tags=["cameras"])


def camera_out(camera: Camera) -> CameraOut:
    return CameraOut(
        id=camera.id,
        image_width_px=camera.image_width_px,
        image_height_px=camera.image_height_px,
        person_height_m=camera.person_height_m,
        equal_focal=camera.equal_focal,
        # Rounded on the way out too: cameras stored before conversions were rounded hold 1.8288000000000002.
        distance_threshold_m=round(camera.distance_threshold_m, CONVERTED_DECIMALS),
        distance_threshold_ft=metres_to_feet(camera.distance_threshold_m),
        known_focal_px=known_focal(camera),
        principal_point_px=principal_point(camera),
        distortion=None
        if not camera.distortion_coefficients
        else Distortion(model="opencv", coefficients=camera.distortion_coefficients),
        camera_height_m=camera.camera_height_m,
        camera_height_tolerance_m=camera.camera_height_tolerance_m or DEFAULT_CAMERA_HEIGHT_TOLERANCE_M,
        keep_images=camera.keep_images,
        usable_evidence_count=camera.usable_evidence_count,
        created_at=camera.created_at,
        updated_at=camera.updated_at,
        url=camera_url(camera.id),
    )


@router.put(
    "/{camera_id}",
    response_model=CameraOut,
    responses={200: {"description": "Updated"}, 201: {"description": "Created"}},
)
def put_camera(
    camera_id: CameraIdPath,
    body: CameraSettings,
    request: Request,
    response: Response,
    session: SessionDep,
    dispatcher: DispatcherDep,
) -> CameraOut:
    """Create or update a camera (idempotent): 201 when created, 200 when it existed.

    A changed image size makes stored evidence meaningless (other pixels), so the calibration is reset, the
    evidence dropped, and frames still waiting for pose or measuring fail with the reason. A changed principal
    point, known focal length or lens keeps the evidence but withdraws the current calibration (frames wait) and
    forces a re-solve: the old solution belongs to another camera model. A changed height prior, focal
    assumption or camera height keeps the evidence and forces a re-solve; the current calibration stays in use
    until it is replaced. Intrinsics must fit the image (a principal point inside it, a focal length within
    0.05-50 x its longer side), else 422.
    """
    applied = apply_settings(session, camera_id, body)
    session.commit()
    request.app.state.camera_cache.forget(camera_id)
    announce(dispatcher, applied.deliveries)
    if applied.resolve:
        nudge_best_effort("request a re-solve", dispatcher.calibration_requested, camera_id, forced=True)
    response.status_code = status.HTTP_201_CREATED if applied.created else status.HTTP_200_OK
    if applied.created:
        response.headers["Location"] = camera_url(camera_id)
    return camera_out(applied.camera)


@router.get("", response_model=CameraList)
def list_cameras(
    session: ReadSessionDep,
    caller: PrincipalDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Cameras per page.")] = 100,
    after: Annotated[str | None, Query(max_length=128, description="Last id of the previous page.")] = None,
) -> CameraList:
    """Cameras in id order, a page at a time; a key limited to some cameras sees only those."""
    cameras = repository.list_cameras(session, limit=limit, after=after, only=caller.cameras)
    next_after = cameras[-1].id if len(cameras) == limit else None
    return CameraList(items=[camera_out(c) for c in cameras], next_after=next_after)


@router.get("/{camera_id}", response_model=CameraOut)
def get_camera(camera_id: CameraIdPath, session: ReadSessionDep) -> CameraOut:
    return camera_out(require_camera(session, camera_id))


@router.get("/{camera_id}/static-spots", response_model=StaticSpotList)
def get_static_spots(camera_id: CameraIdPath, session: ReadSessionDep, settings: SettingsDep) -> StaticSpotList:
    """Where the camera's detector keeps finding a "person" that has not moved for `static_after_s` of frame time
    (image frames only): a mannequin, a poster, a statue. People found there are measured but give no calibration
    evidence and raise no violation; the list lets an operator check that nobody real was taken for one."""
    require_camera(session, camera_id)
    spots = static_spots(session, camera_id, settings.static_after_s)
    return StaticSpotList(
        static_after_s=settings.static_after_s,
        items=[
            StaticSpotOut(
                box_px=(spot.left_px, spot.top_px, spot.right_px, spot.bottom_px),
                first_seen=spot.first_seen,
                last_seen=spot.last_seen,
                sightings=spot.sightings,
            )
            for spot in spots
        ],
    )


@router.delete("/{camera_id}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response)
def delete_camera(camera_id: CameraIdPath, request: Request, session: SessionDep) -> Response:
    """Delete a camera with all its frames, evidence, calibrations and violation events."""
    require_camera(session, camera_id)
    repository.delete_camera(session, camera_id)
    session.commit()
    request.app.state.camera_cache.forget(camera_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
