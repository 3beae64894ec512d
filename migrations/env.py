"""Alembic environment for posemetry: the models' metadata, and the database chosen in this order:

1. a Connection handed over in Config.attributes["connection"] (tests, or code that already holds one);
2. a URL in Config.attributes["database_url"] (`posemetry db upgrade --url`, service.store.migrate);
3. `alembic -x url=...` on the command line;
4. `sqlalchemy.url` in alembic.ini, if someone sets it there (the shipped file leaves it empty);
5. the service settings (POSEMETRY_DATABASE_URL, else the SQLite file in POSEMETRY_DATA_DIR).

The engine comes from service.store.db so migrations run with the same SQLite pragmas as the service (foreign
keys on, WAL, busy timeout). SQLite cannot ALTER most things in place, so scripts are rendered in batch mode there:
a batch rebuilds a table (create a copy, drop the original), and with foreign keys on, dropping `frames` would
cascade-delete every observation. So on SQLite foreign keys are switched off for the migration (a pragma that
only works outside a transaction) and the result is checked with `PRAGMA foreign_key_check` before committing.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from logging.config import fileConfig

from alembic import context
from sqlalchemy import Connection

from service.settings import get_settings
from service.store.db import make_engine
from service.store.migrate import CONNECTION_ATTRIBUTE, URL_ATTRIBUTE
from service.store.models import Base

config = context.config
if config.config_file_name is not None:  # the `alembic` command with alembic.ini; the service logs its own way
    fileConfig(config.config_file_name, disable_existing_loggers=False)
target_metadata = Base.metadata


def _database_url() -> str:
    url = config.attributes.get(URL_ATTRIBUTE) or context.get_x_argument(as_dictionary=True).get("url")
    return url or config.get_main_option("sqlalchemy.url") or get_settings().database_url


def _configure(connection: Connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",
        compare_type=True,
    )


def run_migrations_offline() -> None:
    """`alembic upgrade --sql`: print the SQL instead of running it."""
    context.configure(
        url=_database_url(),
        target_metadata=target_metadata,
        literal_binds=True,
        dialect_opts={"paramstyle": "named"},
        render_as_batch=_database_url().startswith("sqlite"),
    )
    with context.begin_transaction():
        context.run_migrations()


@contextmanager
def _sqlite_foreign_keys_off(connection: Connection) -> Iterator[None]:
    """See the module docstring. A no-op on PostgreSQL, whose ALTER TABLE works in place."""
    if connection.dialect.name != "sqlite":
        yield
        return
    if connection.in_transaction():
        raise RuntimeError("SQLite migrations need a connection outside a transaction (to switch foreign keys off)")
    raw = connection.connection.driver_connection
    raw.execute("PRAGMA foreign_keys=OFF")  # type: ignore[union-attr]
    try:
        yield
    finally:
        raw.execute("PRAGMA foreign_keys=ON")  # type: ignore[union-attr]


def _run(connection: Connection) -> None:
    with _sqlite_foreign_keys_off(connection):
        _configure(connection)
        with context.begin_transaction():
            context.run_migrations()
            if connection.dialect.name == "sqlite":
                broken = connection.exec_driver_sql("PRAGMA foreign_key_check").all()
                if broken:
                    raise RuntimeError(f"migration left rows that break foreign keys: {broken[:5]}")
        if connection.in_transaction():
            connection.commit()


def run_migrations_online() -> None:
    connection = config.attributes.get(CONNECTION_ATTRIBUTE)
    if connection is not None:
        _run(connection)
        return
    engine = make_engine(_database_url(), busy_timeout_s=get_settings().database_busy_timeout_s)
    try:
        with engine.connect() as connection:
            _run(connection)
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
