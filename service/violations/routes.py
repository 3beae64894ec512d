"""Violation counts per minute or hour over a time window."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response

from service.cameras.service import require_camera
from service.http.dependencies import CameraIdPath, ReadSessionDep
from service.http.problems import ProblemError
from service.http.schemas import TimestampText
from service.pictures.service import heatmap_png
from service.render.heatmap import ViolationPoint
from service.violations import repository
from service.violations.repository import HOUR_S, MINUTE_S
from service.violations.schemas import ViolationBucketOut, ViolationCounts

router = APIRouter(prefix="/v1/cameras", tags=["violations"])

BUCKET_S = {"minute": MINUTE_S, "hour": HOUR_S}
DEFAULT_WINDOW = {"minute": timedelta(hours=1), "hour": timedelta(days=1)}
# One answer lists at most this many buckets, so a careless `since` cannot make a huge response.
MAX_BUCKETS = 10_000


def _window(since: datetime | None, until: datetime | None, bucket: str) -> tuple[datetime, datetime]:
    """The window in UTC, defaulted from the bucket width, and refused when empty or with too many buckets."""
    until = (until or datetime.now(UTC)).astimezone(UTC)
    if since is None:
        # Near year 1 the default window would start before the first representable instant: it starts there.
        earliest = datetime.min.replace(tzinfo=UTC)
        since = until - DEFAULT_WINDOW[bucket] if until - earliest > DEFAULT_WINDOW[bucket] else earliest
    since = since.astimezone(UTC)
    if since >= until:
        raise ProblemError(
            422, "invalid-window", f"`since` ({since.isoformat()}) must be before `until` ({until.isoformat()})."
        )
    if (until - since).total_seconds() / BUCKET_S[bucket] > MAX_BUCKETS:
        raise ProblemError(
            422,
            "window-too-large",
            f"The window spans more than {MAX_BUCKETS} {bucket}s; narrow it or use a wider bucket.",
        )
    return since, until


SinceQuery = Annotated[
    TimestampText | None,
    Query(description="Window start (RFC 3339 with zone, or Unix seconds). Default: 1 h (minute) / 1 day back."),
]
UntilQuery = Annotated[TimestampText | None, Query(description="Window end, exclusive. Default: now.")]


@router.get("/{camera_id}/violations", response_model=ViolationCounts)
def get_violations(
    camera_id: CameraIdPath,
    session: ReadSessionDep,
    since: SinceQuery = None,
    until: UntilQuery = None,
    bucket: Annotated[Literal["minute", "hour"], Query(description="Bucket width.")] = "minute",
) -> ViolationCounts:
    """How many pairs were closer than the camera's threshold, per UTC-aligned minute or hour."""
    require_camera(session, camera_id)
    since, until = _window(since, until, bucket)
    bucket_s = BUCKET_S[bucket]
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


# The heat map draws at most this many events (the newest), so a busy camera's year stays one quick picture.
HEATMAP_MAX_EVENTS = 50_000


@router.get(
    "/{camera_id}/violations/heatmap.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "The heat map (PNG)"}},
)
def get_violation_heatmap(
    camera_id: CameraIdPath,
    session: ReadSessionDep,
    since: SinceQuery = None,
    until: UntilQuery = None,
    bucket: Annotated[Literal["minute", "hour"], Query(description="Width of the time-strip bars.")] = "minute",
    size_px: Annotated[int, Query(ge=200, le=2000, description="Side of the map in pixels.")] = 800,
) -> Response:
    """Where violations happened on the ground (density, from the measured positions) and when (counts per bucket).

    At most the newest 50 000 events of the window are drawn.
    """
    require_camera(session, camera_id)
    since, until = _window(since, until, bucket)
    places = repository.violation_places(session, camera_id, since=since, until=until, limit=HEATMAP_MAX_EVENTS)
    session.rollback()
    points = [ViolationPoint.between(p.timestamp, p.ground_i_m, p.ground_j_m) for p in places]
    png = heatmap_png(camera_id, points, since=since, until=until, bucket=bucket, size_px=size_px)
    return Response(png, media_type="image/png")
