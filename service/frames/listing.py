"""A camera's frames a page at a time, newest first: the keyset query and its opaque cursor.

Pages are ordered by capture time (`timestamp`), then frame id, both descending, so frames with the same timestamp
still have one order and no frame is skipped or repeated between pages while new frames arrive. The cursor names
the last frame of a page by that pair; the index (camera_id, timestamp, id) makes every page one range scan,
whatever the camera's history. Status filters use the same scan (or the planner's pick of the status index for the
rare statuses); time filters bound it.
"""

from __future__ import annotations

import base64
import binascii
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime

from sqlalchemy import and_, func, or_, select
from sqlalchemy.orm import Session

from service.store.models import Frame, FrameImage, ViolationEvent

_CURSOR_SEPARATOR = "~"


class BadCursorError(ValueError):
    """A `before` cursor this service did not hand out (or one mangled on the way)."""


@dataclass(frozen=True)
class FramePosition:
    """Where a page ends: the (timestamp, id) of its last frame."""

    timestamp: datetime
    frame_id: uuid.UUID

    def encode(self) -> str:
        """Opaque to clients (base64url of the UTC instant in microseconds and the id)."""
        micros = round(self.timestamp.astimezone(UTC).timestamp() * 1_000_000)
        raw = f"{micros}{_CURSOR_SEPARATOR}{self.frame_id.hex}".encode()
        return base64.urlsafe_b64encode(raw).decode().rstrip("=")

    @classmethod
    def decode(cls, cursor: str) -> FramePosition:
        try:
            raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode("ascii")
            micros, frame_hex = raw.split(_CURSOR_SEPARATOR)
            if not micros.lstrip("-").isdigit() or len(frame_hex) != 32:
                raise ValueError(raw)
            # Exact integer arithmetic: the stored timestamps have microseconds, which a float of seconds loses.
            seconds, fraction = divmod(int(micros), 1_000_000)
            timestamp = datetime.fromtimestamp(seconds, UTC).replace(microsecond=fraction)
            return cls(timestamp, uuid.UUID(hex=frame_hex))
        except (ValueError, UnicodeDecodeError, binascii.Error, OverflowError, OSError):
            raise BadCursorError(cursor) from None


@dataclass(frozen=True)
class ListedFrame:
    """A frame of a page with what its summary shows beyond the row: violations counted, image kept."""

    frame: Frame
    violations: int | None
    """Pairs under the threshold, once measured (None before)."""
    image_kept: bool


def list_frames(
    session: Session,
    camera_id: str,
    *,
    limit: int,
    before: FramePosition | None = None,
    status: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> list[ListedFrame]:
    """Up to `limit` frames of the camera, newest first, after `before`, with timestamp in [since, until)."""
    conditions = [Frame.camera_id == camera_id]
    if status is not None:
        conditions.append(Frame.status == status)
    if since is not None:
        conditions.append(Frame.timestamp >= since)
    if until is not None:
        conditions.append(Frame.timestamp < until)
    if before is not None:
        # Spelled as a range on timestamp and a tie-break, which both backends turn into one index range scan.
        conditions.append(Frame.timestamp <= before.timestamp)
        conditions.append(
            or_(
                Frame.timestamp < before.timestamp,
                and_(Frame.timestamp == before.timestamp, Frame.id < before.frame_id),
            )
        )
    stmt = select(Frame).where(*conditions).order_by(Frame.timestamp.desc(), Frame.id.desc()).limit(limit)
    frames = list(session.scalars(stmt))
    ids = [frame.id for frame in frames]
    counts = _violation_counts(session, ids)
    kept = _kept_images(session, ids)
    return [
        ListedFrame(frame, counts.get(frame.id, 0) if frame.status == "done" else None, frame.id in kept)
        for frame in frames
    ]


def _violation_counts(session: Session, frame_ids: Sequence[uuid.UUID]) -> dict[uuid.UUID, int]:
    if not frame_ids:
        return {}
    stmt = (
        select(ViolationEvent.frame_id, func.count())
        .where(ViolationEvent.frame_id.in_(frame_ids))
        .group_by(ViolationEvent.frame_id)
    )
    return {frame_id: int(count) for frame_id, count in session.execute(stmt)}


def _kept_images(session: Session, frame_ids: Sequence[uuid.UUID]) -> set[uuid.UUID]:
    if not frame_ids:
        return set()
    return set(session.scalars(select(FrameImage.frame_id).where(FrameImage.frame_id.in_(frame_ids))))


def frame_id_by_client_id(session: Session, camera_id: str, client_frame_id: str) -> uuid.UUID | None:
    """The id of the camera's frame posted with this client `frame_id` (unique per camera), or None."""
    stmt = select(Frame.id).where(Frame.camera_id == camera_id, Frame.client_frame_id == client_frame_id)
    return session.execute(stmt).scalar_one_or_none()
