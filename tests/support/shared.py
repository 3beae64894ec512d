"""Where the tests find the real model weights and camera frames (never copied into the repository).

`POSEMETRY_MODEL_DIR` (the service's own setting) wins; otherwise the checkout's sibling `../shared/models`, as
on the CI machine. Tests that need a directory skip, naming it, only when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SHARED_MODELS = REPO.parent / "shared" / "models"
SHARED_DATA = REPO.parent / "shared" / "data"
TOWN_CENTRE = SHARED_DATA / "oxford_town_centre"


def model_dir_path() -> Path:
    return Path(os.environ.get("POSEMETRY_MODEL_DIR", str(SHARED_MODELS))).expanduser()


def require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        pytest.skip(f"{what} directory {path} is absent")
    return path
