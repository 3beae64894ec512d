"""Violation counts per minute or hour over a time window."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Annotated, Literal

from fastapi import APIRouter, Query
from pydantic import AwareDatetime

from service.problems import ProblemError
from service.schemas import ViolationBucketOut, ViolationCounts
from service.store import repository
from service.store.repository import HOUR_S, MINUTE_S

from .common import CameraIdPath, ReadSessionDep, require_camera

router = APIRouter(prefix="/v1/cameras", tags=["violations"])

BUCKET_S = {"minute": MINUTE_S, "hour": HOUR_S}
DEFAULT_WINDOW = {"minute": timedelta(hours=1), "hour": timedelta(days=1)}
# One answer lists at most this many buckets, so a careless `since` cannot make a huge response.
MAX_BUCKETS = 10_000


@router.get("/{camera_id}/violations", response_model=ViolationCounts)
def get_violations(
    camera_id: CameraIdPath,
    session: ReadSessionDep,
    since: Annotated[
        AwareDatetime | None, Query(description="Window start (RFC 3339 with zone). Default: 1 h (minute) / 1 day.")
    ] = None,
    until: Annotated[AwareDatetime | None, Query(description="Window end, exclusive. Default: now.")] = None,
    bucket: Annotated[Literal["minute", "hour"], Query(description="Bucket width.")] = "minute",
) -> ViolationCounts:
    """How many pairs were closer than the camera's threshold, per UTC-aligned minute or hour."""
    require_camera(session, camera_id)
    until = (until or datetime.now(UTC)).astimezone(UTC)
    since = (since or until - DEFAULT_WINDOW[bucket]).astimezone(UTC)
    if since >= until:
        raise ProblemError(
            422, "invalid-window", f"`since` ({since.isoformat()}) must be before `until` ({until.isoformat()})."
        )
    bucket_s = BUCKET_S[bucket]
    if (until - since).total_seconds() / bucket_s > MAX_BUCKETS:
        raise ProblemError(
            422,
            "window-too-large",
            f"The window spans more than {MAX_BUCKETS} {bucket}s; narrow it or use bucket=hour.",
        )
    counts = repository.violation_counts(session, camera_id, since=since, until=until, bucket_s=bucket_s)
    return ViolationCounts(
        camera_id=camera_id,
        since=since,
        until=until,
        bucket=bucket,
        bucket_s=bucket_s,
        total=sum(c.count for c in counts),
        buckets=[ViolationBucketOut(start=c.start, count=c.count) for c in counts],
    )
