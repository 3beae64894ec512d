"""The geometry benchmark end to end, on a few trials: called as a function and through the CLI."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.geometry import EXPERIMENTS, BenchmarkOptions, parse_only, run_benchmark
from bench.report import ReportTable
from service.cli import app


def _numbers(cells: list[str]) -> list[float]:
    """The mean of each 'mean (median)' cell."""
    return [float(cell.split()[0]) for cell in cells]


def _rows(table: ReportTable, label: str) -> list[list[str]]:
    return [row for row in table.rows if row[1] == label]


def test_paper_tables_and_outliers_from_a_function_call() -> None:
    report = run_benchmark(BenchmarkOptions(trials=3, workers=1, only=("table3", "outliers")))
    assert not report.unexpected_errors
    assert any("CPUs" in line for line in report.header)
    table3, outliers = report.tables
    assert table3.title.startswith("Table 3")
    assert table3.columns[2:] == ["5 people", "10 people", "20 people", "50 people", "100 people"]
    # Published numbers sit next to ours, with a half-of-paper check per cell.
    assert _rows(table3, "paper Ours")[0][2:] == ["21.03", "14.15", "8.17", "6.36", "5.27"]
    assert _rows(table3, "paper Baseline")[0][2] == "21.53"
    assert {cell for row in _rows(table3, "linear <= Ours/2") for cell in row[2:]} <= {"yes", "NO"}
    fx_linear = _numbers(_rows(table3, "linear")[0][2:])
    assert all(0.0 <= v < 100.0 for v in fx_linear)
    fail = _rows(table3, "linear")[-1][2:]
    assert all(0.0 <= float(v) <= 100.0 for v in fail)

    assert outliers.title.startswith("Outliers")
    assert [row[0] for row in outliers.rows] == ["20", "20", "100", "100"]
    default_rows = [row for row in outliers.rows if row[1] == "default"]
    for row in default_rows:
        ratio = float(row[outliers.columns.index("ratio")])
        assert ratio > 0
        assert row[outliers.columns.index("<= 1.5")] == ("yes" if ratio <= 1.5 else "NO")


def test_noise_free_scenes_are_recovered_to_machine_precision() -> None:
    (table,) = run_benchmark(BenchmarkOptions(trials=1, workers=1, only=("noise-free",))).tables
    assert len(table.rows) == 12 * 2
    assert table.column("< 1e-06") == ["yes"] * 24, table.rows


def test_results_are_reproducible_and_independent_of_workers() -> None:
    serial = run_benchmark(BenchmarkOptions(trials=3, seed=5, workers=1, only=("distance",)))
    parallel = run_benchmark(BenchmarkOptions(trials=3, seed=5, workers=2, only=("distance",)))
    other = run_benchmark(BenchmarkOptions(trials=3, seed=6, workers=1, only=("distance",)))
    assert serial.tables[0].rows == parallel.tables[0].rows
    assert serial.tables[0].rows != other.tables[0].rows


def test_only_accepts_known_names_in_canonical_order() -> None:
    assert parse_only("timing, table1") == ("table1", "timing")
    assert parse_only(None) == EXPERIMENTS
    with pytest.raises(ValueError, match="nope"):
        parse_only("table1,nope")


def test_cli_prints_tables_and_writes_markdown(tmp_path: Path) -> None:
    markdown = tmp_path / "docs" / "geometry.md"
    result = CliRunner().invoke(
        app,
        [
            "bench",
            "geometry",
            "--trials",
            "3",
            "--workers",
            "1",
            "--only",
            "surveillance,timing",
            "--repeats",
            "1",
            "--markdown",
            str(markdown),
        ],
    )
    assert result.exit_code == 0, result.output
    for text in ("posemetry geometry benchmark", "CPUs", "Surveillance preset", "Timing", "median ms", "p90 ms"):
        assert text in result.output
    assert "Table 1" not in result.output
    written = markdown.read_text()
    assert written.startswith("# Geometry benchmark")
    assert "### Timing" in written
    assert "| method | people | median ms | p90 ms | target ms | pass |" in written
    assert "| linear | 1000 |" in written


def test_cli_rejects_unknown_experiments() -> None:
    result = CliRunner().invoke(app, ["bench", "geometry", "--only", "table9"])
    assert result.exit_code == 2
    assert "table9" in result.output


def test_cli_version() -> None:
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0
    assert result.output.startswith("posemetry ")


def test_capped_experiment_keeps_every_setting_aligned(monkeypatch: pytest.MonkeyPatch) -> None:
    """An experiment that runs fewer trials than --trials (distortion) still fills every row of its table."""
    import bench.geometry as bench

    monkeypatch.setattr(bench, "DISTORTION_MAX_TRIALS", 1)
    (table,) = run_benchmark(BenchmarkOptions(trials=2, workers=1, only=("distortion",))).tables
    assert len(table.rows) == 16
    for row in table.rows:
        assert all(cell not in ("-", "- (-)") for cell in row), row
