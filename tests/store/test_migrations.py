"""The Alembic migrations build exactly the schema the models describe, on both backends."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import inspect
from typer.testing import CliRunner

from service.cli import app
from service.settings import get_settings
from service.store import make_engine
from service.store.migrate import current_revision, head_revision, schema_differences, upgrade
from service.store.models import Base

TABLES = {"cameras", "frames", "observations", "calibrations", "violation_events"}


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
