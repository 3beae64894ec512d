"""Where the tests find the real model weights and camera frames (never copied into the repository).

Models: `POSEMETRY_MODEL_DIR` (the service's own setting) wins. Data: `POSEMETRY_TEST_DATA_DIR` (a folder laid out
like `shared/data`: `oxford_town_centre/`, ...) wins. Otherwise both are the checkout's siblings `../shared/models`
and `../shared/data`, as on the CI machine, so a clone placed anywhere else runs the data tests by setting the two.
Tests that need a directory skip, naming it, only when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SHARED_MODELS = REPO.parent / "shared" / "models"
TEST_DATA_DIR_ENV = "POSEMETRY_TEST_DATA_DIR"


def data_dir_path() -> Path:
    return Path(os.environ.get(TEST_DATA_DIR_ENV) or str(REPO.parent / "shared" / "data")).expanduser()


def model_dir_path() -> Path:
    return Path(os.environ.get("POSEMETRY_MODEL_DIR", str(SHARED_MODELS))).expanduser()


SHARED_DATA = data_dir_path()
TOWN_CENTRE = SHARED_DATA / "oxford_town_centre"


def require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        pytest.skip(f"{what} directory {path} is absent (set {TEST_DATA_DIR_ENV} / POSEMETRY_MODEL_DIR)")
    return path
