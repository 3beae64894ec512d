"""`posemetry bench` comes from the `posemetry.commands` entry point: there when bench is installed, left out
where its package is not (the Docker image), and an error when it is there but broken."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from service.cli import ENTRY_POINT_GROUP, add_command_groups, app


@pytest.fixture
def on_path(tmp_path: Path) -> Iterator[Path]:
    sys.path.insert(0, str(tmp_path))
    yield tmp_path
    sys.path.remove(str(tmp_path))
    sys.modules.pop("broken_plugin", None)


def test_bench_is_a_group_of_the_installed_command() -> None:
    result = CliRunner().invoke(app, ["bench", "--help"])
    assert result.exit_code == 0, result.output
    assert "geometry" in result.output and "load" in result.output


def test_a_group_whose_package_is_not_installed_is_left_out() -> None:
    ghost = EntryPoint("ghost", "ghost_package_not_installed.cli:group", ENTRY_POINT_GROUP)
    bench = EntryPoint("bench", "bench.cli:bench_app", ENTRY_POINT_GROUP)
    assert add_command_groups(typer.Typer(), [ghost, bench]) == ["bench"]


def test_a_group_that_is_installed_but_broken_is_an_error(on_path: Path) -> None:
    (on_path / "broken_plugin.py").write_text("import a_dependency_that_is_missing\n")
    broken = EntryPoint("broken", "broken_plugin:group", ENTRY_POINT_GROUP)
    with pytest.raises(ModuleNotFoundError, match="a_dependency_that_is_missing"):
        add_command_groups(typer.Typer(), [broken])
