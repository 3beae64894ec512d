"""Revision 0013 adds observations.client_track_id (nullable) and drops it again, keeping every frame and person, on
both backends."""

from __future__ import annotations

import pytest
from alembic import command
from sqlalchemy import text

from service.store import make_engine
from service.store.migrate import alembic_config, upgrade
from tests.support.store import insert_raw_camera_and_frame, observation_columns

pytestmark = pytest.mark.both_backends

FRAME_ID = "00000000-0000-0000-0000-000000000001"


def test_0013_adds_the_client_track_id_column_and_downgrades_without_losing_people(database_url: str) -> None:
    upgrade(database_url, "0012")
    engine = make_engine(database_url)
    try:
        with engine.begin() as connection:
            insert_raw_camera_and_frame(connection, people=1, client_frame_id="f-1")
        assert "client_track_id" not in observation_columns(database_url)
        upgrade(database_url, "0013")
        assert "client_track_id" in observation_columns(database_url)
        with engine.begin() as connection:
            frame_id = FRAME_ID.replace("-", "") if connection.dialect.name == "sqlite" else FRAME_ID
            connection.execute(
                text(
                    "INSERT INTO observations (camera_id, frame_id, person_index, usable, unusable_reason, "
                    "client_track_id) "
                    "VALUES ('c', :frame, 0, false, 'posted without ankles', :track)"
                ),
                {"frame": frame_id, "track": "x" * 64},
            )
        with engine.connect() as connection:
            stored = connection.execute(text("SELECT client_track_id FROM observations")).scalars().all()
            assert stored == ["x" * 64]
        command.downgrade(alembic_config(database_url), "0012")
        assert "client_track_id" not in observation_columns(database_url)
        with engine.connect() as connection:
            assert connection.execute(text("SELECT client_frame_id FROM frames")).scalars().all() == ["f-1"]
            assert connection.execute(text("SELECT person_index FROM observations")).scalars().all() == [0]
    finally:
        engine.dispose()
    upgrade(database_url)
