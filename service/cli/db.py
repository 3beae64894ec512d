"""`posemetry db`: the SQL store's schema migrations (Alembic), on SQLite or PostgreSQL."""

from __future__ import annotations

import typer
from rich.console import Console

db_app = typer.Typer(help="The SQL store: schema migrations.", no_args_is_help=True)


@db_app.command("upgrade")
def db_upgrade(
    revision: str = typer.Argument("head", help="Alembic revision to migrate to."),
    url: str | None = typer.Option(
        None, help="Database URL (default: POSEMETRY_DATABASE_URL, else the SQLite file in POSEMETRY_DATA_DIR)."
    ),
) -> None:
    """Create or migrate the database schema; safe to run on every start (a no-op when up to date)."""
    from alembic.util import CommandError
    from sqlalchemy.exc import SQLAlchemyError

    from service.settings import get_settings
    from service.store import make_engine
    from service.store.migrate import current_revision, upgrade

    settings = get_settings()
    database_url = url or settings.database_url
    try:
        upgrade(database_url, revision, script_location=settings.migrations_dir)
        engine = make_engine(database_url, busy_timeout_s=settings.database_busy_timeout_s)
        try:
            with engine.connect() as connection:
                now = current_revision(connection)
        finally:
            engine.dispose()
    except (SQLAlchemyError, CommandError, FileNotFoundError, ValueError) as exc:
        Console(stderr=True).print(f"[red]db upgrade failed:[/red] {exc}", highlight=False)
        raise typer.Exit(1) from None
    typer.echo(f"{_display_url(database_url)} is at revision {now}")


def migrate(database_url: str) -> None:
    """Bring the database to the newest revision (`posemetry serve` does on every start)."""
    from service.settings import get_settings
    from service.store.migrate import upgrade

    upgrade(database_url, "head", script_location=get_settings().migrations_dir)


def _display_url(url: str) -> str:
    """The URL with its password masked: command output ends up in logs."""
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)
