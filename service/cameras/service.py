"""Cameras as a process: what changing a camera's settings does to its evidence and calibration, and the 404."""

from __future__ import annotations

import uuid
from dataclasses import dataclass

from sqlalchemy.orm import Session

from service.calibration.repository import current_calibration, reset_calibration
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


def apply_settings(session: Session, camera_id: str, body: CameraSettings) -> SettingsApplied:
    """Create or update a camera in the caller's transaction.

    A changed image size makes stored evidence meaningless (other pixels), so the calibration is reset, the
    evidence dropped, and frames still waiting for pose or measuring fail with the reason. A changed height prior,
    focal assumption or known focal length keeps the evidence and asks for a forced re-solve; the current
    calibration stays in use until it is replaced. A camera that stops keeping images forgets the ones it kept
    (privacy).
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
        delete_kept_images(session, camera_id)
    resolve = False
    deliveries: list[uuid.UUID] = []
    if old is not None:
        if old[:2] != (body.image_width_px, body.image_height_px):
            was_calibrated = current_calibration(session, camera_id) is not None
            reset_calibration(session, camera_id, drop_evidence=True, reason="image_size_changed")
            fail_unfinished_frames(
                session,
                camera_id,
                f"camera {camera_id!r} was resized to {body.image_width_px}x{body.image_height_px} px before this "
                "frame was measured",
            )
            if was_calibrated:
                deliveries = status_changed_deliveries(session, camera_id, None, "calibrated", "image size changed")
        elif old[2:] != (body.person_height_m, body.equal_focal, body.known_focal_px):
            resolve = True
    return SettingsApplied(camera, created, deliveries, resolve)
