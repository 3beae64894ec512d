"""A stored frame measured in place, as the measuring job would (service.frames.service.frame_outcomes, then the
outcome stored with its violation events), in the caller's transaction: for API tests that need a measured frame
without running a worker."""

from __future__ import annotations

from sqlalchemy.orm import Session

from service.domain import FrameOutcome
from service.frames.repository import frame_observations, record_frame_outcomes
from service.frames.service import frame_outcomes
from service.store.models import CalibrationVersion, Camera, Frame


def process_frame(session: Session, frame: Frame, camera: Camera, calibration: CalibrationVersion) -> FrameOutcome:
    """Measure one stored frame and store its result and violation events in the caller's transaction."""
    outcome = frame_outcomes([frame], [frame_observations(session, frame.id)], camera, calibration)[0]
    record_frame_outcomes(session, [outcome])
    return outcome
