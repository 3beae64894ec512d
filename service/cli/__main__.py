"""`python -m service.cli`: the `posemetry` command."""

from service.cli import app

app()
