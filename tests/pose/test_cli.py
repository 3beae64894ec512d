"""`posemetry models check`: a table of every file, exit status 1 naming the fix when any is missing or corrupt."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from service.pose.cli import models_app
from service.pose.model_files import REGISTRY, THUNDER


def test_check_passes_on_the_pinned_files(model_dir: Path) -> None:
    result = CliRunner().invoke(models_app, ["check", "--dir", str(model_dir)])
    assert result.exit_code == 0, result.output
    assert result.output.count("ok") >= 3


def test_check_fails_and_names_the_fix(tmp_path: Path) -> None:
    result = CliRunner().invoke(models_app, ["check", "--dir", str(tmp_path)])
    assert result.exit_code == 1
    assert "missing" in result.output and "posemetry models fetch --dir" in result.output


def test_check_prints_whole_cells_in_a_pipe(tmp_path: Path) -> None:
    """Piped (CliRunner's output is no terminal), the table is not cut to 80 columns: names, sizes, licences and a
    corrupt file's status come out whole."""
    (tmp_path / THUNDER.file_name).write_bytes(b"\0" * THUNDER.size_bytes)
    result = CliRunner().invoke(models_app, ["check", "--dir", str(tmp_path)], env={"COLUMNS": ""})
    assert result.exit_code == 1
    assert "…" not in result.output.replace("…, expected", "").replace("…)", ""), result.output
    for spec in REGISTRY.values():
        row = next(line for line in result.output.splitlines() if spec.file_name in line)
        assert spec.key in row and f"{spec.size_bytes:,}" in row and spec.licence in row, row
    thunder = next(line for line in result.output.splitlines() if THUNDER.file_name in line)
    assert f"expected {THUNDER.sha256[:12]}…)" in thunder, thunder
