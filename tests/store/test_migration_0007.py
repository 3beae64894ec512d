"""Revision 0007 adds frames.content_sha256 (nullable) and drops it again, keeping every frame, on both backends."""

from __future__ import annotations

import pytest
from alembic import command
from sqlalchemy import inspect, text

from service.store import make_engine
from service.store.migrate import alembic_config, upgrade

pytestmark = pytest.mark.both_backends

FRAME_ID = {
    "sqlite": "00000000000000000000000000000001",
    "postgresql": "00000000-0000-0000-0000-000000000001",
}


def _frame_columns(url: str) -> set[str]:
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return {column["name"] for column in inspect(connection).get_columns("frames")}
    finally:
        engine.dispose()


def test_0007_adds_the_digest_column_and_downgrades_without_losing_frames(database_url: str, backend: str) -> None:
    upgrade(database_url, "0006")
    engine = make_engine(database_url)
    try:
        with engine.begin() as connection:
            connection.execute(
                text(
                    "INSERT INTO cameras (id, image_width_px, image_height_px, person_height_m, equal_focal, "
                    "distance_threshold_m, created_at, updated_at) VALUES ('c', 640, 480, 1.3, true, 1.8, "
                    "'2026-01-01 00:00:00', '2026-01-01 00:00:00')"
                )
            )
            connection.execute(
                text(
                    "INSERT INTO frames (id, camera_id, client_frame_id, timestamp, received_at, source, status, "
                    "people) VALUES (:id, 'c', 'f-1', '2026-01-01 00:00:00', '2026-01-01 00:00:00', 'keypoints', "
                    "'pending', 0)"
                ),
                {"id": FRAME_ID[backend]},
            )
        assert "content_sha256" not in _frame_columns(database_url)
        upgrade(database_url, "0007")
        assert "content_sha256" in _frame_columns(database_url)
        with engine.begin() as connection:
            # A frame stored before the revision has no digest (its retries are judged as before).
            assert connection.execute(text("SELECT client_frame_id, content_sha256 FROM frames")).all() == [
                ("f-1", None)
            ]
            connection.execute(text("UPDATE frames SET content_sha256 = :d"), {"d": "ab" * 32})
        command.downgrade(alembic_config(database_url), "0006")
        assert "content_sha256" not in _frame_columns(database_url)
        with engine.connect() as connection:
            assert connection.execute(text("SELECT client_frame_id FROM frames")).scalars().all() == ["f-1"]
    finally:
        engine.dispose()
    upgrade(database_url)
