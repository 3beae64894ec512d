"""The `posemetry` command line: one typer app, with a sub-app per area (bench, db; serve, api, worker later).

Heavy imports (numpy, scipy, the geometry) happen inside the commands so that
`posemetry --help` and unrelated commands stay fast.
"""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console

from service import __version__

app = typer.Typer(
    name="posemetry",
    help="Camera auto-calibration and physical distances from human pose.",
    no_args_is_help=True,
    add_completion=False,
)
bench_app = typer.Typer(help="Benchmarks: accuracy against the paper's protocol, and speed.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
db_app = typer.Typer(help="The SQL store: schema migrations.", no_args_is_help=True)
app.add_typer(db_app, name="db")

QUICK_TRIALS = 50
DEFAULT_TRIALS = 1000
_PIPED_WIDTH = 220


def _version(value: bool) -> None:
    if value:
        typer.echo(f"posemetry {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    """Camera auto-calibration and physical distances from human pose."""


@bench_app.command("geometry")
def bench_geometry(
    trials: int | None = typer.Option(
        None, min=1, help=f"Monte Carlo trials per setting (default {DEFAULT_TRIALS}; {QUICK_TRIALS} with --quick)."
    ),
    seed: int = typer.Option(0, min=0, help="Root seed; every scene derives from it, so runs are reproducible."),
    workers: int = typer.Option(2, min=1, help="Processes for the accuracy experiments (timing runs in one)."),
    quick: bool = typer.Option(False, "--quick", help=f"Smoke run: {QUICK_TRIALS} trials per setting."),
    only: str | None = typer.Option(
        None,
        help="Comma-separated experiments: noise-free, table1, table2, table3, outliers, distance, "
        "surveillance, timing (default: all).",
    ),
    repeats: int = typer.Option(50, min=1, help="Timed calls per timing case."),
    markdown: Path | None = typer.Option(None, help="Also write the tables as Markdown to this file."),
) -> None:
    """Accuracy of calibrate() on simulated scenes (paper Sect. 4.1, Tables 1-3) and its speed."""
    from service.bench.geometry import BenchmarkOptions, parse_only, run_benchmark
    from service.bench.report import markdown_document, to_rich

    try:
        selected = parse_only(only)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--only") from None
    options = BenchmarkOptions(
        trials=trials if trials is not None else (QUICK_TRIALS if quick else DEFAULT_TRIALS),
        seed=seed,
        workers=workers,
        only=selected,
        repeats=repeats,
    )
    console = Console()
    if not console.is_terminal:
        # Piped or captured output would otherwise be cut at 80 columns and truncate the tables' cells.
        console = Console(width=_PIPED_WIDTH)
    log = Console(stderr=True)
    report = run_benchmark(options, progress=lambda message: log.print(f"[dim]{message}[/dim]", highlight=False))
    console.print("posemetry geometry benchmark", style="bold")
    for line in report.header:
        console.print(line, highlight=False)
    for table in report.tables:
        console.print()
        console.print(to_rich(table))
    if markdown is not None:
        markdown.parent.mkdir(parents=True, exist_ok=True)
        markdown.write_text(markdown_document("Geometry benchmark", report.header, report.tables))
        console.print(f"\nwrote {markdown}", highlight=False)
    if report.unexpected_errors:
        for line in report.unexpected_errors:
            log.print(f"[red]unexpected exception[/red] {line}", highlight=False)
        raise typer.Exit(1)


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


def _display_url(url: str) -> str:
    """The URL with its password masked: command output ends up in logs."""
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


if __name__ == "__main__":
    app()
