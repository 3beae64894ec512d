"""Analyze fixtures: the real pose models and camera data, skipped (naming the folder) only when absent."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir


@pytest.fixture(scope="session")
def models() -> Path:
    return require_dir(model_dir_path(), "pose model")


@pytest.fixture(scope="session")
def town() -> Path:
    return require_dir(TOWN_CENTRE, "Oxford Town Centre data")
