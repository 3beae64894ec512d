"""The Alembic migrations build exactly the schema the models describe, on both backends."""

from __future__ import annotations

from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, inspect
from typer.testing import CliRunner

from service.calibration.evidence import sample_key
from service.cli import app
from service.settings import get_settings
from service.store import make_engine
from service.store.migrate import alembic_config, current_revision, upgrade
from service.store.models import Base
from tests.support.store import insert_raw_camera_and_frame


def head_revision() -> str | None:
    return ScriptDirectory.from_config(alembic_config()).get_current_head()


def schema_differences(connection: Connection) -> list[object]:
    """What autogenerate would change to make the database match the models: empty when they agree."""
    context = MigrationContext.configure(connection, opts={"compare_type": True, "compare_server_default": False})
    return list(compare_metadata(context, Base.metadata))


pytestmark = pytest.mark.both_backends

TABLES = {"cameras", "frames", "frame_images", "observations", "calibrations", "violation_events", "api_keys"}
TABLES |= {"movement_monitors"}
WEBHOOK_TABLES = {
    "webhook_subscriptions",
    "webhook_events",
    "webhook_deliveries",
    "webhook_attempts",
    "violation_cooldowns",
}
TABLES |= WEBHOOK_TABLES
TABLES |= {"static_spots"}


def test_upgrade_builds_the_models_schema(database_url: str) -> None:
    upgrade(database_url)
    engine = make_engine(database_url)
    try:
        with engine.connect() as connection:
            assert current_revision(connection) == head_revision()
            assert schema_differences(connection) == []
            assert TABLES <= set(inspect(connection).get_table_names())
    finally:
        engine.dispose()


def test_upgrade_is_idempotent_and_downgrade_removes_everything(database_url: str) -> None:
    from alembic import command

    from service.store.migrate import alembic_config

    upgrade(database_url)
    upgrade(database_url)  # a no-op at head
    command.downgrade(alembic_config(database_url), "base")
    engine = make_engine(database_url)
    try:
        with engine.connect() as connection:
            assert set(inspect(connection).get_table_names()) & TABLES == set()
    finally:
        engine.dispose()
    upgrade(database_url)


def test_models_and_migrations_cover_the_same_tables() -> None:
    assert set(Base.metadata.tables) == TABLES


def test_cli_db_upgrade_from_any_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`posemetry db upgrade` finds the migrations relative to the package and the database from the settings."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    monkeypatch.setenv("POSEMETRY_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.delenv("POSEMETRY_DATABASE_URL", raising=False)
    get_settings.cache_clear()
    try:
        result = CliRunner().invoke(app, ["db", "upgrade"])
    finally:
        get_settings.cache_clear()
    assert result.exit_code == 0, result.output
    assert f"is at revision {head_revision()}" in result.output
    assert (tmp_path / "data" / "posemetry.sqlite3").is_file()


def test_cli_db_upgrade_reports_an_unreachable_database(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["db", "upgrade", "--url", "postgresql://user:secret@127.0.0.1:9/none"])
    assert result.exit_code == 1
    assert "secret" not in result.output


def test_0002_packs_stored_keypoints_and_unpacks_them_on_downgrade(database_url: str) -> None:
    """Keypoints stored as JSON before revision 0002 survive the move to packed float32, and the way back.

    The way back also passes 0006, which must key the people stored unkeyed before sample_key is NOT NULL again.
    """
    import json

    from alembic import command
    from sqlalchemy import text
    from sqlalchemy.orm import Session

    from service.store import Observation
    from service.store.migrate import alembic_config

    keypoints = [[100.25 + k, 200.5 - k, k / 17] for k in range(17)]
    upgrade(database_url, "0001")
    engine = make_engine(database_url)
    try:
        with engine.begin() as connection:
            insert_raw_camera_and_frame(connection, people=2)
            frame_id = connection.execute(text("SELECT id FROM frames")).scalar_one()
            for index, value in enumerate((json.dumps(keypoints), None)):
                connection.execute(
                    text(
                        "INSERT INTO observations (camera_id, frame_id, person_index, keypoints, usable, "
                        "unusable_reason, sample_key) VALUES ('c', :frame, :index, :kp, false, 'test', 1)"
                    ),
                    {"frame": frame_id, "index": index, "kp": value},
                )
        upgrade(database_url)
        with Session(engine) as session:
            stored = session.query(Observation).order_by(Observation.person_index).all()
            assert stored[1].keypoints is None
            assert stored[0].keypoints is not None
            for got, want in zip(stored[0].keypoints, keypoints, strict=True):
                assert got == pytest.approx(want, abs=1e-4)
            stored[1].sample_key = None  # stored since 0006 and not keyed yet: the downgrade must key it
            session.commit()
        command.downgrade(alembic_config(database_url), "0001")
        with engine.connect() as connection:
            keys = connection.execute(text("SELECT sample_key FROM observations ORDER BY person_index")).scalars()
            ids = connection.execute(text("SELECT id FROM observations ORDER BY person_index")).scalars()
            assert list(keys) == [1, sample_key(list(ids)[1])]
            rows = connection.execute(text("SELECT keypoints FROM observations ORDER BY person_index")).all()
        restored = rows[0][0] if isinstance(rows[0][0], list) else json.loads(rows[0][0])
        assert rows[1][0] is None
        for got, want in zip(restored, keypoints, strict=True):
            assert got == pytest.approx(want, abs=1e-4)
    finally:
        engine.dispose()
    upgrade(database_url)
