"""Alembic, driven from code: `posemetry db upgrade` and the tests build their Config here, without alembic.ini.

The migration scripts live in `migrations/` at the repository root (the layout the project uses), next to the
`service` package. They are found relative to the package, not the working directory, so `posemetry db
upgrade` works from anywhere in a source checkout or an editable install (`pip install -e .`, what README and
the Docker image use). A plain wheel install does not carry them: point the `migrations_dir` setting
(POSEMETRY_MIGRATIONS_DIR) at a copy.
"""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.migration import MigrationContext
from sqlalchemy import Connection

# Config.attributes keys that migrations/env.py reads.
URL_ATTRIBUTE = "database_url"
CONNECTION_ATTRIBUTE = "connection"


def migrations_dir(override: Path | None = None) -> Path:
    """The Alembic script directory: `override` when given, else `migrations/` beside the service package."""
    path = override if override is not None else Path(__file__).resolve().parents[2] / "migrations"
    if not (path / "env.py").is_file():
        raise FileNotFoundError(
            f"no Alembic migrations at {path}: run from a source checkout or editable install, "
            "or set POSEMETRY_MIGRATIONS_DIR to the repository's migrations/ directory"
        )
    return path


def alembic_config(
    database_url: str | None = None, connection: Connection | None = None, *, script_location: Path | None = None
) -> Config:
    """A Config for the given database (or the settings' one when neither is given).

    The URL travels in Config.attributes rather than the `sqlalchemy.url` option, which is parsed with
    ConfigParser interpolation and would mangle passwords containing '%'.
    """
    config = Config()
    config.set_main_option("script_location", str(migrations_dir(script_location)))
    if database_url is not None:
        config.attributes[URL_ATTRIBUTE] = database_url
    if connection is not None:
        config.attributes[CONNECTION_ATTRIBUTE] = connection
    return config


def upgrade(
    database_url: str | None = None,
    revision: str = "head",
    *,
    connection: Connection | None = None,
    script_location: Path | None = None,
) -> None:
    """Migrate the database to `revision` (creating the schema on an empty database)."""
    command.upgrade(alembic_config(database_url, connection, script_location=script_location), revision)


def current_revision(connection: Connection) -> str | None:
    return MigrationContext.configure(connection).get_current_revision()
