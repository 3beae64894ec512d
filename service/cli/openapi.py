"""`posemetry openapi`: regenerate (or check) the committed OpenAPI document."""

from __future__ import annotations

import typer


def openapi(
    check: bool = typer.Option(False, "--check", help="Only compare; exit 1 when the committed file is stale."),
) -> None:
    """Write openapi/openapi.json from the app's routes and schemas (a test fails when it is stale)."""
    from service.openapi import OPENAPI_PATH, is_current, write

    if check:
        if not is_current():
            typer.echo(f"{OPENAPI_PATH} is stale: run posemetry openapi", err=True)
            raise typer.Exit(1)
        typer.echo(f"{OPENAPI_PATH} is up to date")
        return
    typer.echo(f"wrote {write()}")
