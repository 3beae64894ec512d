"""Revision 0012 adds observations.appearance (nullable) and drops it again, keeping every frame, on both backends."""

from __future__ import annotations

import pytest
from alembic import command
from sqlalchemy import text

from service.store import make_engine
from service.store.migrate import alembic_config, upgrade
from tests.support.store import insert_raw_camera_and_frame, observation_columns

pytestmark = pytest.mark.both_backends


def test_0012_adds_the_appearance_column_and_downgrades_without_losing_frames(database_url: str) -> None:
    upgrade(database_url, "0011")
    engine = make_engine(database_url)
    try:
        with engine.begin() as connection:
            insert_raw_camera_and_frame(connection, people=0, client_frame_id="f-1")
        assert "appearance" not in observation_columns(database_url)
        upgrade(database_url, "0012")
        assert "appearance" in observation_columns(database_url)
        command.downgrade(alembic_config(database_url), "0011")
        assert "appearance" not in observation_columns(database_url)
        with engine.connect() as connection:
            assert connection.execute(text("SELECT client_frame_id FROM frames")).scalars().all() == ["f-1"]
    finally:
        engine.dispose()
    upgrade(database_url)
