"""Revision 0007 adds frames.content_sha256 (nullable) and drops it again, keeping every frame, on both backends."""

from __future__ import annotations

import pytest
from alembic import command
from sqlalchemy import inspect, text

from service.store import make_engine
from service.store.migrate import alembic_config, upgrade
from tests.support.store import insert_raw_camera_and_frame

pytestmark = pytest.mark.both_backends


def _frame_columns(url: str) -> set[str]:
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return {column["name"] for column in inspect(connection).get_columns("frames")}
    finally:
        engine.dispose()


def test_0007_adds_the_digest_column_and_downgrades_without_losing_frames(database_url: str) -> None:
    upgrade(database_url, "0006")
    engine = make_engine(database_url)
    try:
        with engine.begin() as connection:
            insert_raw_camera_and_frame(connection, people=0, client_frame_id="f-1")
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
