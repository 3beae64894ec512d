"""Image frames as a process: find the people in a stored picture and store them as the frame's people.

`detect_people` is what the pose job runs (workers.jobs.detect_people is its RQ adapter). The estimator is loaded
once per worker process (`load_pose_estimator` caches it). A picture that cannot be analysed, or missing model
files, fail this frame with the reason, not the worker. People are stored only while the frame is still
`detecting`, so a pose job that runs twice (a retry after a crash) stores them once.

A calibrated camera's frames are searched the calibrated way: the camera's current calibration predicts how tall a
person appears on every row, so the detector looks at each band of the frame at the scale that makes its people
the detector's favourite size and skips rows above the horizon (service/pose/regions.py). An uncalibrated camera's
frames are searched in bands sized by the whole standing people its latest frames showed (SEEN_FRAMES), and where
those do not say how tall people appear where (its first frames, a view without a floor), by the people the frame's
own first pass finds, or the fixed policy for an unknown view.
"""

from __future__ import annotations

import logging
import time
import uuid
from typing import TYPE_CHECKING

import numpy as np

from service.calibration.camera_model import calibration_from_version
from service.calibration.repository import current_calibration
from service.cameras.static_spots import observe
from service.domain import DONE, FAILED, GONE, SKIPPED, PersonIn
from service.frames.images import ImageError, decode
from service.frames.ingest import record_detection_failure, record_detections
from service.frames.keypoints import as_static, people_from_detections
from service.frames.repository import frame_image, seen_people_boxes
from service.observability.logs import JOBS_LOGGER, log_context
from service.observability.metrics import POSE_INFERENCE
from service.observability.request_id import request_id_context
from service.settings import Settings
from service.store.models import Camera, Frame
from service.store.sessions import read_session_factory, transaction

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

    from service.geometry import Calibration
    from service.queue import RedisDispatcher

log = logging.getLogger(JOBS_LOGGER)

SEEN_FRAMES = 5
"""An uncalibrated camera's latest image frames whose usable people size the next frame's search. Town Centre shows
6-9 usable people per frame: five frames give the size plane 30-45 people over the view's depth, and a camera that
was turned is sized by its new view five frames later."""


def detect_people(
    settings: Settings, dispatcher: RedisDispatcher, frame_uuid: uuid.UUID, *, measure: bool = True
) -> str:
    """Run pose inference on an image frame, store its people (the image goes unless the camera keeps images),
    then have the camera's pending frames measured (`measure` False: the caller measures them itself). Its log
    lines carry the request id of the request that posted the image."""
    frame_id = str(frame_uuid)
    with read_session_factory(settings)() as session:
        frame = session.get(Frame, frame_uuid)
        if frame is None:
            return GONE  # its camera was deleted after the frame was queued
        if frame.status != "detecting":
            # A duplicate run, or the retry of a run whose process died after storing the people and before it
            # asked for them to be measured: ask again (deduplicated per camera, so a duplicate costs nothing).
            if frame.status == "pending":
                dispatcher.measure_requested([frame.camera_id])
            return SKIPPED
        camera = session.get(Camera, frame.camera_id)
        image = frame_image(session, frame_uuid)
        data = None if image is None else image.data
        request_id = frame.request_id
        guide = None if camera is None else _guide(session, camera)
        seen = (
            None
            if camera is None or guide is not None
            else seen_people_boxes(session, camera.id, camera.epoch, SEEN_FRAMES)
        )
    if camera is None:
        return GONE
    # The frame's own request id: also right for a job queued again by a starting worker, which has no meta.
    with request_id_context(request_id), log_context(camera_id=camera.id, frame_id=frame_id):
        outcome = _detect(settings, dispatcher, frame_uuid, camera, data, guide, seen)
    if outcome == DONE and measure:
        dispatcher.measure_requested([camera.id])
    return outcome


def camera_of(settings: Settings, frame_uuid: uuid.UUID) -> str | None:
    """The camera of a stored frame (None: gone)."""
    with read_session_factory(settings)() as session:
        frame = session.get(Frame, frame_uuid)
        return None if frame is None else frame.camera_id


def _mark_static(
    session: Session, frame_uuid: uuid.UUID, camera_id: str, people: list[PersonIn], static_after_s: float
) -> list[PersonIn]:
    """The frame's people, those standing at one of the camera's static spots marked so (cameras.static_spots)."""
    frame = session.get(Frame, frame_uuid)
    if frame is None or frame.status != "detecting":
        return people  # a duplicate run: record_detections stores nothing, so no sighting is counted twice
    static = observe(session, camera_id, frame.timestamp, [person.box_px for person in people], static_after_s)
    return [as_static(person) if still else person for person, still in zip(people, static, strict=True)]


def _guide(session: Session, camera: Camera) -> Calibration | None:
    """The camera's current calibration, to guide the detector; None while it has none."""
    version = current_calibration(session, camera.id)
    if version is None:
        return None
    return calibration_from_version(version, (camera.image_width_px, camera.image_height_px))


def _detect(
    settings: Settings,
    dispatcher: RedisDispatcher,
    frame_uuid: uuid.UUID,
    camera: Camera,
    data: bytes | None,
    guide: Calibration | None,
    seen: list[tuple[float, ...]] | None,
) -> str:
    from service.pose.model_files import ModelFilesError
    from service.pose.pipeline import load_pose_estimator

    try:
        if data is None:
            raise ImageError("the frame's image is no longer stored")
        _header, bgr = decode(data, max_pixels=settings.max_image_pixels)
        estimator = load_pose_estimator(settings)
        started = time.perf_counter()
        found = estimator(bgr, guide, seen_boxes_px=np.asarray(seen, dtype=np.float64).reshape(-1, 4) if seen else None)
        inference_s = time.perf_counter() - started
    except (ImageError, ModelFilesError) as exc:
        log.warning("pose of frame %s of camera %s failed: %s", frame_uuid, camera.id, exc)
        with transaction(settings) as session:
            record_detection_failure(session, frame_uuid, str(exc))
        return FAILED
    POSE_INFERENCE.labels(model=estimator.name).observe(inference_s)
    size = (camera.image_width_px, camera.image_height_px)
    people = people_from_detections(found[: settings.max_people_per_frame], size)
    with transaction(settings) as session:
        people = _mark_static(session, frame_uuid, camera.id, people, settings.static_after_s)
        stored = record_detections(session, frame_uuid, people, pose_model=estimator.name)
    if stored is None:
        return SKIPPED
    log.info(
        "frame %s of camera %s: %d people found in %.0f ms (%s)",
        frame_uuid,
        camera.id,
        len(people),
        inference_s * 1000,
        f"sized by the {estimator.last_sizing}" if estimator.last_sizing != "fixed passes" else "fixed passes",
        extra={
            "people": len(people),
            "inference_ms": round(inference_s * 1000, 1),
            "pose_model": estimator.name,
            "guided": guide is not None,
            "sizing": estimator.last_sizing,
        },
    )
    return DONE
