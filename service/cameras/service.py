"""Cameras as a process: what changing a camera's settings does to its evidence and calibration, and the 404."""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session

from service.calibration.repository import current_calibration, reset_calibration, withdraw_current
from service.cameras import repository
from service.cameras.schemas import CameraSettings
from service.frames.repository import delete_kept_images, fail_unfinished_frames
from service.http.links import camera_url
from service.http.problems import ProblemError
from service.store.models import Camera
from service.webhooks.events import status_changed_deliveries


def camera_not_found(camera_id: str) -> ProblemError:
    return ProblemError(
        404, "camera-not-found", f"No camera {camera_id!r}: create it with PUT {camera_url(camera_id)}."
    )


def require_camera(session: Session, camera_id: str) -> Camera:
    """The camera, or the 404 problem that says how to create it."""
    camera = repository.get_camera(session, camera_id)
    if camera is None:
        raise camera_not_found(camera_id)
    return camera


@dataclass(frozen=True)
class SettingsApplied:
    """What `apply_settings` did: the camera, whether it is new, the webhook deliveries it raised (to queue after
    the commit) and whether the camera needs a forced re-solve."""

    camera: Camera
    created: bool
    deliveries: list[uuid.UUID]
    resolve: bool


def camera_model_columns(body: CameraSettings) -> dict[str, Any]:
    """The settings' optional camera model as the camera row's columns (known_focal_px itself is fx)."""
    focal = body.known_focal_xy_px
    pp = body.principal_point_px
    height_given = body.camera_height_m is not None
    return {
        "known_focal_y_px": focal[1] if focal is not None and isinstance(body.known_focal_px, tuple) else None,
        "principal_point_x_px": None if pp is None else pp[0],
        "principal_point_y_px": None if pp is None else pp[1],
        "distortion_coefficients": None if body.distortion is None else list(body.distortion.coefficients),
        "camera_height_m": body.camera_height_m,
        "camera_height_tolerance_m": body.camera_height_tolerance_m if height_given else None,
    }


def _intrinsics(camera: Camera) -> tuple[object, ...]:
    """What a solution is expressed in: a change makes the current solution a different camera."""
    return (
        camera.known_focal_px,
        camera.known_focal_y_px,
        camera.principal_point_x_px,
        camera.principal_point_y_px,
        camera.distortion_coefficients,
    )


def _priors(camera: Camera) -> tuple[object, ...]:
    """What a solve assumes about the people and the scale: a change asks for a re-solve on the same evidence."""
    return (camera.person_height_m, camera.equal_focal, camera.camera_height_m, camera.camera_height_tolerance_m)


def apply_settings(session: Session, camera_id: str, body: CameraSettings) -> SettingsApplied:
    """Create or update a camera in the caller's transaction.

    A changed image size makes stored evidence meaningless (other pixels), so the calibration is reset (a new
    epoch), the evidence dropped, and frames still waiting for pose or measuring fail with the reason. A changed
    principal point, known focal length or lens keeps the evidence (the same pixels, the same epoch) but
    withdraws the current calibration and forces a re-solve: the current solution was found for another camera
    model, and measuring with it (a principal point the user has just corrected, say) would mix the two; frames
    wait for the re-solve instead. A changed height prior, focal assumption or camera height keeps the evidence
    and the current calibration in use, and forces a re-solve that replaces it. A camera that stops keeping
    images forgets the ones it kept (privacy).
    """
    before = repository.get_camera(session, camera_id)
    before_keeps_images = before is not None and before.keep_images
    old = None
    if before is not None:
        old = ((before.image_width_px, before.image_height_px), _intrinsics(before), _priors(before))
    camera, created = repository.upsert_camera(
        session,
        camera_id,
        image_width_px=body.image_width_px,
        image_height_px=body.image_height_px,
        person_height_m=body.person_height_m,
        equal_focal=body.equal_focal,
        distance_threshold_m=body.distance_threshold.metres,
        known_focal_px=None if body.known_focal_xy_px is None else body.known_focal_xy_px[0],
        keep_images=body.keep_images,
        camera_model=camera_model_columns(body),
    )
    if before_keeps_images and not body.keep_images:
        delete_kept_images(session, camera_id)
    resolve = False
    deliveries: list[uuid.UUID] = []
    if old is not None:
        size_changed = old[0] != (body.image_width_px, body.image_height_px)
        if size_changed or old[1] != _intrinsics(camera):
            reason = "image size changed" if size_changed else "camera model changed"
            was_calibrated = current_calibration(session, camera_id) is not None
            if size_changed:
                reset_calibration(session, camera_id, drop_evidence=True, reason="image_size_changed")
                fail_unfinished_frames(
                    session,
                    camera_id,
                    f"camera {camera_id!r} was resized to {body.image_width_px}x{body.image_height_px} px before "
                    "this frame was measured",
                )
            else:
                withdraw_current(session, camera_id)
            if was_calibrated:
                deliveries = status_changed_deliveries(session, camera_id, None, "calibrated", reason)
            resolve = not size_changed
        elif old[2] != _priors(camera):
            resolve = True
    return SettingsApplied(camera, created, deliveries, resolve)
