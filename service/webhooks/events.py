"""Raising webhook events where things happen: measured frames with violations, a new current calibration, a
camera's calibration status changing. Each function runs inside the caller's transaction and returns the ids of
the deliveries it stored; the caller queues them after committing (SQL first, queue second: `announce`).

Nothing is computed or stored when no enabled subscription wants the event, so cameras nobody subscribed to pay
one small query per batch.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Sequence
from datetime import datetime, timedelta

from sqlalchemy.orm import Session

from service.dispatch import UNAVAILABLE_ERRORS, Dispatcher
from service.domain import FrameOutcome, metres_to_feet
from service.http.links import frame_url
from service.settings import Settings
from service.store.models import CalibrationVersion, Camera, utc_now
from service.webhooks import repository as store

from .cooldown import Candidate
from .payloads import (
    CalibrationStatusChanged,
    CalibrationStatusChangedData,
    CalibrationUpdated,
    CalibrationUpdatedData,
    CameraStatus,
    FrameRef,
    PairAlert,
    ViolationData,
    ViolationDetected,
    calibration_fields,
    feet,
)

log = logging.getLogger(__name__)

VIOLATION_DETECTED = "violation.detected"
CALIBRATION_UPDATED = "calibration.updated"
CALIBRATION_STATUS_CHANGED = "calibration.status_changed"


def first_attempts(delivery_ids: Sequence[uuid.UUID]) -> list[tuple[uuid.UUID, int, datetime | None]]:
    """New deliveries as the dispatcher takes them: attempt 1 of each, now."""
    return [(delivery_id, 1, None) for delivery_id in delivery_ids]


def announce(dispatcher: Dispatcher, deliveries: Sequence[uuid.UUID]) -> None:
    """Queue committed deliveries' first attempts; if the queue is down they stay pending in SQL, and the workers'
    sweep queues them (so this never fails the caller)."""
    if not deliveries:
        return
    try:
        dispatcher.deliveries_due(first_attempts(deliveries))
    except UNAVAILABLE_ERRORS as exc:
        log.warning("could not queue %d webhook deliveries (the sweep will): %s", len(deliveries), exc)


def _candidates(outcome: FrameOutcome) -> list[Candidate]:
    """The frame's violating pairs with both people's ground positions (a pair with someone unplaced has none)."""
    return [
        Candidate(v.person_i, v.person_j, v.ground_i_m, v.ground_j_m)
        for v in outcome.violations
        if v.ground_i_m is not None and v.ground_j_m is not None
    ]


def violation_deliveries(
    session: Session,
    camera: Camera,
    outcomes: Sequence[FrameOutcome],
    settings: Settings,
    *,
    client_frame_ids: dict[uuid.UUID, str | None] | None = None,
) -> list[uuid.UUID]:
    """`violation.detected` for each measured frame with a pair under the threshold that the cooldown lets
    through (service.webhooks.cooldown), one event per frame; the cooldown state is updated alongside."""
    frames = sorted((o for o in outcomes if o.status == "done" and o.violations), key=lambda o: o.timestamp)
    if not frames:
        return []
    subscriptions = store.subscriptions_for(session, VIOLATION_DETECTED, camera.id)
    if not subscriptions or session.get(Camera, camera.id) is None:
        return []  # nobody listens, or the camera was deleted while its frames were measured
    window_s, radius_m = settings.webhook_cooldown_s, settings.webhook_cooldown_radius_m
    earliest = frames[0].timestamp - timedelta(seconds=window_s)
    cooldown = store.load_cooldown(session, camera.id, since=earliest, window_s=window_s, radius_m=radius_m)
    now = utc_now()
    threshold_m = camera.distance_threshold_m
    deliveries: list[uuid.UUID] = []
    for outcome in frames:
        stds = {(v.person_i, v.person_j): v for v in outcome.violations}
        fired = cooldown.admit(outcome.timestamp, _candidates(outcome))
        if not fired:
            continue
        pairs = []
        for c in fired:
            v = stds[(c.i, c.j)]
            pairs.append(
                PairAlert(
                    i=c.i,
                    j=c.j,
                    distance_m=v.distance_m,
                    distance_ft=feet(v.distance_m),  # type: ignore[arg-type]
                    distance_std_m=v.distance_std_m,
                    distance_std_ft=feet(v.distance_std_m),
                    ground_i_m=c.a,
                    ground_j_m=c.b,
                    track_id_i=v.track_id_i,
                    track_id_j=v.track_id_j,
                )
            )
        event = ViolationDetected(
            timestamp=now,
            data=ViolationData(
                camera_id=camera.id,
                frame=FrameRef(
                    id=outcome.frame_id,
                    client_frame_id=(client_frame_ids or {}).get(outcome.frame_id),
                    timestamp=outcome.timestamp,
                    url=frame_url(camera.id, outcome.frame_id),
                ),
                calibration_version=outcome.calibration_version or 0,
                distance_threshold_m=threshold_m,
                distance_threshold_ft=metres_to_feet(threshold_m),
                violation_count=len(outcome.violations),
                pairs=pairs,
                cooldown_s=window_s,
            ),
        )
        deliveries += store.raise_event(
            session,
            event_type=VIOLATION_DETECTED,
            camera_id=camera.id,
            body=event.model_dump_json(),
            subscriptions=subscriptions,
            dedupe_key=f"violation:{outcome.frame_id}",
            now=now,
        )
    store.save_cooldown(session, camera.id, cooldown, forget_before=cooldown.expired_before(frames[-1].timestamp))
    return deliveries


def calibration_deliveries(
    session: Session, camera_id: str, current: CalibrationVersion, previous: CalibrationVersion | None
) -> list[uuid.UUID]:
    """`calibration.updated` for a version that just became current, and `calibration.status_changed` when it
    is the camera's first (the camera was uncalibrated)."""
    now = utc_now()
    fields = calibration_fields(camera_id, current)
    updated = store.subscriptions_for(session, CALIBRATION_UPDATED, camera_id)
    deliveries = []
    if updated:
        event = CalibrationUpdated(
            timestamp=now,
            data=CalibrationUpdatedData(**fields, previous_version=None if previous is None else previous.version),
        )
        deliveries += store.raise_event(
            session,
            event_type=CALIBRATION_UPDATED,
            camera_id=camera_id,
            body=event.model_dump_json(),
            subscriptions=updated,
            dedupe_key=f"calibration:{camera_id}:{current.version}:{current.created_at.isoformat()}",
            now=now,
        )
    if previous is None:
        deliveries += status_changed_deliveries(session, camera_id, current, "uncalibrated", "calibrated")
    return deliveries


def status_changed_deliveries(
    session: Session,
    camera_id: str,
    current: CalibrationVersion | None,
    previous_status: CameraStatus,
    reason: str,
) -> list[uuid.UUID]:
    """`calibration.status_changed`: the camera is now calibrated with `current`, or uncalibrated (None)."""
    subscriptions = store.subscriptions_for(session, CALIBRATION_STATUS_CHANGED, camera_id)
    if not subscriptions:
        return []
    now = utc_now()
    event = CalibrationStatusChanged(
        timestamp=now,
        data=CalibrationStatusChangedData(
            **calibration_fields(camera_id, current), previous_status=previous_status, reason=reason
        ),
    )
    return store.raise_event(
        session,
        event_type=CALIBRATION_STATUS_CHANGED,
        camera_id=camera_id,
        body=event.model_dump_json(),
        subscriptions=subscriptions,
        now=now,
    )
