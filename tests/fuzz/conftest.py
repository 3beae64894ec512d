"""Fuzz fixtures: the seeded world (tests/fuzz/world.py), a fresh copy per test, and the closing table of counts.

Run the fuzz tests alone, with the counts, and longer than CI does:
    POSEMETRY_FUZZ_EXAMPLES=500 .venv/bin/python -m pytest tests/fuzz -q -p no:randomly
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.fuzz.tally import TALLY
from tests.fuzz.world import FuzzWorld, WorldTemplate, open_world, seed_template
from tests.support.databases import sqlite_template

__all__ = ["sqlite_template"]


@pytest.fixture(scope="session")
def world_template(sqlite_template: Path, tmp_path_factory: pytest.TempPathFactory) -> WorldTemplate:
    database = tmp_path_factory.mktemp("fuzz-world") / "template.sqlite3"
    shutil.copyfile(sqlite_template, database)
    return seed_template(database)


@pytest.fixture
def world(world_template: WorldTemplate, tmp_path: Path) -> FuzzWorld:
    return open_world(world_template, tmp_path)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    lines = TALLY.lines()
    if lines:
        terminalreporter.section("hostile input: cases tried")
        for line in lines:
            terminalreporter.write_line(line)
