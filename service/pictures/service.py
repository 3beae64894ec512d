"""The PNG pictures the API serves, drawn from stored rows: a frame's overlay and top-down map, a camera's heat map.

This module only gathers what `service.render` needs (the kept image, the frame's result and people, the
calibration version that measured it, violation positions) and encodes the PNG; the drawing lives in
`service.render`. The caller reads the rows in a read-only session and handles "not found" as HTTP.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Literal

import numpy as np

from service.calibration.camera_model import calibration_from_version
from service.frames.schemas import FrameResult
from service.render.frame import FramePictures
from service.render.heatmap import ViolationPoint, render_heatmap
from service.render.png import encode_png
from service.store.models import CalibrationVersion, Camera, Frame, Observation

Unit = Literal["m", "ft"]
HeatmapBucket = Literal["minute", "hour", "day"]


@dataclass(frozen=True)
class StoredFrame:
    """A frame with what drawing it needs, read in one session."""

    frame: Frame
    camera: Camera
    people: Sequence[Observation]
    calibration: CalibrationVersion | None
    """The version that measured the frame (None while it is not measured)."""


def _result(stored: StoredFrame) -> FrameResult | None:
    return None if stored.frame.result is None else FrameResult.model_validate(stored.frame.result)


def _unmeasured(threshold_m: float) -> FrameResult:
    """The result of a frame nobody has measured yet: its people are drawn, without positions or distances."""
    return FrameResult(calibration_version=0, distance_threshold_m=threshold_m, people=[], pairs=[], violations=[])


def overlay_png(stored: StoredFrame, image_data: bytes, *, unit: Unit = "m") -> bytes:
    """The kept frame image with the ground grid, people coloured by the threshold and nearest-neighbour links."""
    import cv2

    image = cv2.imdecode(np.frombuffer(image_data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError("the stored image no longer decodes")
    camera = stored.camera
    size = (camera.image_width_px, camera.image_height_px)
    calibration = None if stored.calibration is None else calibration_from_version(stored.calibration, size)
    result = _result(stored) or _unmeasured(camera.distance_threshold_m)
    return encode_png(FramePictures.of(result, stored.people, calibration, unit).overlay(image))


def topdown_png(stored: StoredFrame, *, unit: Unit = "m", size_px: int = 800) -> bytes:
    """A map of where the frame's people stand (needs a measured frame)."""
    result = _result(stored)
    if result is None or stored.calibration is None:
        raise ValueError("the frame has not been measured yet")
    camera = stored.camera
    calibration = calibration_from_version(stored.calibration, (camera.image_width_px, camera.image_height_px))
    pictures = FramePictures.of(result, stored.people, calibration, unit)
    return encode_png(pictures.topdown(size_px=size_px, title=picture_title(camera.id, stored.frame.timestamp)))


def picture_title(camera_id: str, timestamp: datetime | None = None) -> str:
    """'camera lobby   2026-11-22 10:00:00 UTC': what a picture shows, so a saved copy still says it."""
    when = "" if timestamp is None else f"   {timestamp.astimezone(UTC):%Y-%m-%d %H:%M:%S} UTC"
    return f"camera {camera_id}{when}"


def heatmap_png(
    camera_id: str,
    violations: Sequence[ViolationPoint],
    *,
    since: datetime,
    until: datetime,
    bucket: HeatmapBucket,
    size_px: int = 800,
) -> bytes:
    """Where and when a camera's violations happened in a window: ground density above, counts per bucket below."""
    title = picture_title(camera_id)
    return encode_png(render_heatmap(violations, start=since, end=until, bucket=bucket, size_px=size_px, title=title))
