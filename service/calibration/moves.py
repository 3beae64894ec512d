"""Watching a calibrated camera for a move while its frames are measured (the measuring job's side of
service.calibration.movement).

Every chunk of frames the measuring job takes is first shown to the movement test, in frame-time order, with the
camera's current calibration as the reference. Without an alarm the frames are measured and the test's state is
kept for the next chunk (`movement_monitors`, one row per camera, valid for one epoch: a newer current version
moves it onto its own reference). With an alarm the frames from the change point
on are left unmeasured, the camera's next epoch opens (service.calibration.repository.open_epoch_after_move), and
the frames already measured since the change point wait to be measured again with the new epoch's calibration.
"""

from __future__ import annotations

import copy
import logging
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from service.calibration.movement import Alarm, FrameEvidence, MovementMonitor, ReferenceCamera, frames_evidence
from service.calibration.repository import open_epoch_after_move, save_movement_state
from service.geometry import DEFAULT_HEIGHT_STD_M
from service.observability.logs import JOBS_LOGGER
from service.store.models import CalibrationVersion, Camera, Frame
from service.store.models import MovementMonitor as StoredMonitor
from service.webhooks.events import status_changed_deliveries

log = logging.getLogger(JOBS_LOGGER)


def reference_for(version: CalibrationVersion) -> ReferenceCamera:
    """The movement test's reference camera for a stored (successful) calibration version."""
    normal = (version.normal_x, version.normal_y, version.normal_z)
    return ReferenceCamera.of(
        (version.fx_px, version.fy_px, version.cx_px, version.cy_px),  # type: ignore[arg-type]
        normal,  # type: ignore[arg-type]
        rho_m=float(version.rho_m),  # type: ignore[arg-type]
        person_height_m=version.person_height_m,
        height_std_m=DEFAULT_HEIGHT_STD_M,
        noise_px=version.noise_px,
    )


# The test's state takes every frame, but its statistic is computed once per this many frames of a chunk: the
# statistic over all candidate change points was a fifth of a measuring job's time when computed after every frame
# under load (50-frame chunks). A step whose test alarms is replayed frame by frame, so a move is found with the
# same frame and dated at the same change point as before. A camera that keeps up sends chunks of a frame or two.
TEST_EVERY_FRAMES = 8


@dataclass(frozen=True)
class Watched:
    """What the test made of a chunk: its state to keep, and the move it found (None: the view is unchanged)."""

    state: bytes
    statistic: float
    move: Alarm | None
    detected_at: datetime | None
    """The timestamp of the frame with which the test crossed its threshold (moved_at is the change point's)."""

    @property
    def moved_at(self) -> datetime | None:
        return None if self.move is None else datetime.fromtimestamp(self.move.timestamp_s, UTC)


def watch(
    calibration: CalibrationVersion,
    stored: StoredMonitor | None,
    frames: Sequence[Frame],
    people: dict[Any, list[Any]],
) -> Watched:
    """Show the chunk's frames to the movement test, oldest frame time first, stopping at an alarm.

    The test's state lives as long as the epoch: a newer calibration version moves it onto its own reference
    (MovementMonitor.rebased) rather than starting again, so a move never hides behind a fresh solve."""
    camera = reference_for(calibration)
    if stored is None or stored.epoch != calibration.epoch:
        monitor = MovementMonitor.start(camera)
    else:
        monitor = MovementMonitor.from_bytes(stored.state)
        if stored.calibration_version != calibration.version:
            monitor = monitor.rebased(camera)
    ordered = sorted(frames, key=lambda frame: (frame.timestamp, frame.id))
    tops, bottoms, index = [], [], []
    for k, frame in enumerate(ordered):
        for person in people.get(frame.id, []):
            if person.usable:
                tops.append((person.shoulder_x_px, person.shoulder_y_px))
                bottoms.append((person.ankle_x_px, person.ankle_y_px))
                index.append(k)
    evidence = frames_evidence(
        camera,
        np.array(tops, float).reshape(-1, 2),
        np.array(bottoms, float).reshape(-1, 2),
        np.array(index, int),
        len(ordered),
    )
    paired = list(zip(ordered, evidence, strict=True))
    for start in range(0, len(paired), TEST_EVERY_FRAMES):
        step = paired[start : start + TEST_EVERY_FRAMES]
        before = copy.deepcopy(monitor) if len(step) > 1 else None
        alarm = _observe(monitor, step)
        if alarm is not None and before is not None:
            # Found within the step: replay it frame by frame from the state before it, so the alarm, its change
            # point and the frame it is found with are exactly what testing after every frame gives.
            monitor = before
            for frame, frame_evidence in step:
                alarm = _observe(monitor, [(frame, frame_evidence)])
                if alarm is not None:
                    return Watched(monitor.to_bytes(), monitor.last_statistic, alarm, frame.timestamp)
        elif alarm is not None:
            return Watched(monitor.to_bytes(), monitor.last_statistic, alarm, step[0][0].timestamp)
    return Watched(monitor.to_bytes(), monitor.last_statistic, None, None)


def _observe(monitor: MovementMonitor, step: list[tuple[Frame, FrameEvidence]]) -> Alarm | None:
    return monitor.observe(
        [evidence for _, evidence in step],
        [frame.id.bytes for frame, _ in step],
        [frame.timestamp.timestamp() for frame, _ in step],
    )


def keep_watch(session: Session, camera: Camera, calibration: CalibrationVersion, watched: Watched) -> list[uuid.UUID]:
    """In the measuring job's transaction: keep the test's state, or open the next epoch for a move (with its
    `calibration.status_changed` webhook, reason camera_moved); returns the deliveries to announce."""
    if watched.move is None:
        save_movement_state(
            session,
            camera.id,
            epoch=calibration.epoch,
            calibration_version=calibration.version,
            state=watched.state,
            statistic=watched.statistic,
        )
        return []
    first = session.get(Frame, uuid.UUID(bytes=watched.move.frame_id))
    moved_at = first.timestamp if first is not None else watched.moved_at
    if not open_epoch_after_move(session, camera.id, from_epoch=calibration.epoch, moved_at=moved_at):  # type: ignore[arg-type]
        return []
    focal, tilt_1, tilt_2 = watched.move.offset
    log.warning(
        "camera %s moved at %s (found with the frame of %s; statistic %.1f; focal x%.3f, tilt %.2f deg): "
        "epoch %d opened",
        camera.id,
        moved_at.isoformat() if moved_at else None,
        watched.detected_at.isoformat() if watched.detected_at else None,
        watched.move.statistic,
        float(np.exp(focal)),
        float(np.degrees(np.hypot(tilt_1, tilt_2))),
        calibration.epoch + 1,
    )
    return status_changed_deliveries(session, camera.id, None, "calibrated", "camera_moved")
