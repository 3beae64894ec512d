"""The webhook bodies: Standard Webhooks envelopes `{"type", "timestamp", "data"}`, one model per event type.

They are also published in the OpenAPI document's `webhooks` section, so receivers can generate code for them.
`timestamp` is when posemetry raised the event; a violation's frame carries its own capture time.
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, Field

from service.calibration.schemas import CalibrationUncertainty, SolvedCamera, solution_fields
from service.domain import METRES_PER_FOOT

if TYPE_CHECKING:
    from service.store.models import CalibrationVersion

CameraStatus = Literal["uncalibrated", "calibrated"]


def feet(metres: float | None) -> float | None:
    return None if metres is None else metres / METRES_PER_FOOT


class FrameRef(BaseModel):
    """The frame a violation was seen in; `url` is its full result (`GET`)."""

    id: uuid.UUID
    client_frame_id: str | None
    timestamp: datetime = Field(description="When the frame was captured (the client's timestamp).")
    url: str


class PairAlert(BaseModel):
    """Two people closer than the camera's threshold (indices into the frame's `people`), with where they stand."""

    i: int
    j: int
    distance_m: float
    distance_ft: float
    distance_std_m: float | None = Field(description="1-sigma uncertainty of the distance, metres.")
    distance_std_ft: float | None
    ground_i_m: tuple[float, float] = Field(description="Person i on the ground [right, forward], metres.")
    ground_j_m: tuple[float, float] = Field(description="Person j on the ground [right, forward], metres.")
    track_id_i: str | None = Field(default=None, description="Person i's `track_id` as posted; null when none was.")
    track_id_j: str | None = Field(default=None, description="Person j's `track_id` as posted; null when none was.")


class ViolationData(BaseModel):
    """People stood closer than the threshold in one frame. `pairs` are the pairs that raised this alert; pairs
    still in their cooldown (alerted recently, standing where they were) are counted in `violation_count` only."""

    camera_id: str
    frame: FrameRef
    calibration_version: int = Field(description="The calibration version the distances were measured with.")
    distance_threshold_m: float
    distance_threshold_ft: float
    violation_count: int = Field(description="Pairs under the threshold in the frame, alerted or in cooldown.")
    pairs: list[PairAlert]
    cooldown_s: float = Field(description="A pair alerted here raises no new alert for this long while it stays.")


class _CalibrationHeader(BaseModel):
    camera_id: str
    status: CameraStatus
    version: int | None


# pydantic orders inherited fields from the last base to the first: the header's, then the camera's, then the
# class's own, which is the order receivers have always received.
class CalibrationData(SolvedCamera, _CalibrationHeader):
    """A camera's calibration as of the event: the current version's values, or nulls when uncalibrated."""

    uncertainty: CalibrationUncertainty | None
    person_height_m: float | None
    people_used: int | None
    inliers: int | None
    evidence_count: int | None = Field(description="Usable people stored when this version was solved.")
    forced: bool | None
    solved_at: datetime | None


class CalibrationUpdatedData(CalibrationData):
    """A new calibration version became current."""

    previous_version: int | None


class CalibrationStatusChangedData(CalibrationData):
    """The camera went from uncalibrated to calibrated (its first current version) or back (a reset)."""

    previous_status: CameraStatus
    reason: str = Field(
        description="What changed it: `calibrated`, `reset`, `image size changed`, `camera_moved` (the movement "
        "test found that the camera's view changed: a new calibration epoch starts), `camera model changed` (the "
        "principal point, known focal length or lens)."
    )


class ViolationDetected(BaseModel):
    type: Literal["violation.detected"] = "violation.detected"
    timestamp: datetime
    data: ViolationData


class CalibrationUpdated(BaseModel):
    type: Literal["calibration.updated"] = "calibration.updated"
    timestamp: datetime
    data: CalibrationUpdatedData


class CalibrationStatusChanged(BaseModel):
    type: Literal["calibration.status_changed"] = "calibration.status_changed"
    timestamp: datetime
    data: CalibrationStatusChangedData


def calibration_fields(camera_id: str, version: CalibrationVersion | None) -> dict[str, object]:
    """CalibrationData's fields for a current version (None: the camera is uncalibrated)."""
    if version is None:
        empty = dict.fromkeys(set(CalibrationData.model_fields) - {"camera_id", "status"})
        return {"camera_id": camera_id, "status": "uncalibrated", **empty}
    return {
        "camera_id": camera_id,
        "status": "calibrated",
        "version": version.version,
        **solution_fields(version),
        "evidence_count": version.evidence_count,
        "forced": version.forced,
        "solved_at": version.created_at,
    }
