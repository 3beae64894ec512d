"""The workers' backlog read straight from the database: frames not answered yet, and how old the oldest is.

Read-only and cheap: both counts come from the (status, camera_id, received_at) index, and on SQLite a reader
neither waits for nor blocks the writers (WAL).
"""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import func, select

from service.store import Frame, make_engine

WAITING = ("pending", "detecting")


class BacklogReader:
    def __init__(self, database_url: str) -> None:
        self.engine = make_engine(database_url)

    def read(self) -> tuple[int, int, float]:
        """(pending, detecting, age of the oldest of them in seconds; 0 when there are none)."""
        query = (
            select(Frame.status, func.count(), func.min(Frame.received_at))
            .where(Frame.status.in_(WAITING))
            .group_by(Frame.status)
        )
        with self.engine.connect() as connection:
            rows = {status: (count, oldest) for status, count, oldest in connection.execute(query)}
        oldest = [when for _count, when in rows.values() if when is not None]
        age_s = 0.0
        if oldest:
            first = min(when if when.tzinfo else when.replace(tzinfo=UTC) for when in oldest)
            age_s = max((datetime.now(UTC) - first).total_seconds(), 0.0)
        return int(rows.get("pending", (0, None))[0]), int(rows.get("detecting", (0, None))[0]), age_s

    def close(self) -> None:
        self.engine.dispose()
