"""Cameras: idempotent create/update, list, read, delete."""

from __future__ import annotations

import uuid
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status

from service.auth.dependencies import PrincipalDep
from service.schemas import METRES_PER_FOOT, CameraList, CameraOut, CameraSettings
from service.store import repository
from service.store.models import Camera
from service.webhooks.events import first_attempts, status_changed_deliveries

from .common import (
    CameraIdPath,
    DispatcherDep,
    ReadSessionDep,
    SessionDep,
    camera_url,
    nudge_best_effort,
    require_camera,
)

router = APIRouter(prefix="/v1/cameras", tags=["cameras"])


def camera_out(camera: Camera) -> CameraOut:
    return CameraOut(
        id=camera.id,
        image_width_px=camera.image_width_px,
        image_height_px=camera.image_height_px,
        person_height_m=camera.person_height_m,
        equal_focal=camera.equal_focal,
        distance_threshold_m=camera.distance_threshold_m,
        distance_threshold_ft=camera.distance_threshold_m / METRES_PER_FOOT,
        known_focal_px=camera.known_focal_px,
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
    evidence dropped, and frames still waiting for pose or measuring fail with the reason. A changed height prior,
    focal assumption or known focal length keeps the evidence and asks for a forced re-solve; the current
    calibration stays in use until it is replaced.
    """
    before = repository.get_camera(session, camera_id)
    old = None
    before_keeps_images = before is not None and before.keep_images
    if before is not None:
        old = (
            before.image_width_px,
            before.image_height_px,
            before.person_height_m,
            before.equal_focal,
            before.known_focal_px,
        )
    camera, created = repository.upsert_camera(
        session,
        camera_id,
        image_width_px=body.image_width_px,
        image_height_px=body.image_height_px,
        person_height_m=body.person_height_m,
        equal_focal=body.equal_focal,
        distance_threshold_m=body.distance_threshold.metres,
        known_focal_px=body.known_focal_px,
        keep_images=body.keep_images,
    )
    if before_keeps_images and not body.keep_images:
        repository.delete_kept_images(session, camera_id)  # privacy: stopping keeping images forgets the kept ones
    resolve = False
    deliveries: list[uuid.UUID] = []
    if old is not None:
        if old[:2] != (body.image_width_px, body.image_height_px):
            was_calibrated = repository.current_calibration(session, camera_id) is not None
            repository.reset_calibration(session, camera_id, drop_evidence=True)
            repository.fail_unfinished_frames(
                session,
                camera_id,
                f"camera {camera_id!r} was resized to {body.image_width_px}x{body.image_height_px} px before this "
                "frame was measured",
            )
            if was_calibrated:
                deliveries = status_changed_deliveries(session, camera_id, None, "calibrated", "image size changed")
        elif old[2:] != (body.person_height_m, body.equal_focal, body.known_focal_px):
            resolve = True
    session.commit()
    request.app.state.camera_cache.forget(camera_id)
    if deliveries:
        nudge_best_effort("queue webhook deliveries", dispatcher.deliveries_due, first_attempts(deliveries))
    if resolve:
        nudge_best_effort("request a re-solve", dispatcher.calibration_requested, camera_id, forced=True)
    response.status_code = status.HTTP_201_CREATED if created else status.HTTP_200_OK
    if created:
        response.headers["Location"] = camera_url(camera_id)
    return camera_out(camera)


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


@router.delete("/{camera_id}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response)
def delete_camera(camera_id: CameraIdPath, request: Request, session: SessionDep) -> Response:
    """Delete a camera with all its frames, evidence, calibrations and violation events."""
    require_camera(session, camera_id)
    repository.delete_camera(session, camera_id)
    session.commit()
    request.app.state.camera_cache.forget(camera_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
