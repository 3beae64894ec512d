"""The `posemetry` command line: one typer app, a module per command group.

- processes: `serve` (everything on one machine), `api`, `worker`;
- db: `db upgrade`; keys: `keys create|list|revoke`; models (service.pose.cli): `models fetch|check`;
- analyze: `analyze` (offline); openapi: `openapi`.

Other packages add groups through the `posemetry.commands` entry point: `bench` (bench/cli.py) is one, so the
benchmarks stay beside the product and the service never imports them.
"""

from __future__ import annotations

from collections.abc import Iterable
from importlib.metadata import EntryPoint, entry_points

import typer

from service import __version__
from service.pose.cli import models_app

from . import analyze, db, keys, openapi, processes

ENTRY_POINT_GROUP = "posemetry.commands"

app = typer.Typer(
    name="posemetry",
    help="Camera auto-calibration and physical distances from human pose.",
    no_args_is_help=True,
    add_completion=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"posemetry {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    """Camera auto-calibration and physical distances from human pose."""


app.command("serve")(processes.serve)
app.command("api")(processes.api)
app.command("worker")(processes.worker)
app.command("analyze")(analyze.analyze)
app.command("openapi")(openapi.openapi)
app.add_typer(db.db_app, name="db")
app.add_typer(keys.keys_app, name="keys")
app.add_typer(models_app, name="models")


def add_command_groups(app: typer.Typer, entries: Iterable[EntryPoint]) -> list[str]:
    """Add the command groups other packages register; returns their names. A group whose package is not
    installed here is left out (the Docker image carries the service, not the benchmarks), but one that fails to
    import for another reason is an error."""
    added = []
    for entry in sorted(entries, key=lambda entry: entry.name):
        try:
            group = entry.load()
        except ModuleNotFoundError as exc:
            if exc.name != entry.module.split(".")[0]:
                raise
            continue
        app.add_typer(group, name=entry.name)
        added.append(entry.name)
    return added


add_command_groups(app, entry_points(group=ENTRY_POINT_GROUP))
