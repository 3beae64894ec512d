"""The body of `POST /v1/cameras/{camera_id}/distances`: people to measure now (the answer is a FrameResult)."""

from __future__ import annotations

from service.frames.schemas import PersonObservation
from service.http.schemas import StrictModel


class DistanceRequest(StrictModel):
    """People to measure with the camera's current calibration (`POST /v1/cameras/{camera_id}/distances`)."""

    people: list[PersonObservation]
