"""`posemetry models check`: a table of every file, exit status 1 naming the fix when any is missing or corrupt."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from service.pose.cli import models_app


def test_check_passes_on_the_pinned_files(model_dir: Path) -> None:
    result = CliRunner().invoke(models_app, ["check", "--dir", str(model_dir)])
    assert result.exit_code == 0, result.output
    assert result.output.count("ok") >= 3


def test_check_fails_and_names_the_fix(tmp_path: Path) -> None:
    result = CliRunner().invoke(models_app, ["check", "--dir", str(tmp_path)])
    assert result.exit_code == 1
    assert "missing" in result.output and "posemetry models fetch --dir" in result.output
