"""POSEMETRY_TEST_DATA_DIR points the data-dependent tests at a data folder anywhere, as POSEMETRY_MODEL_DIR does
for the models: a clone that is not beside `shared/` runs them instead of skipping them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.shared import REPO, TOWN_CENTRE, require_dir

# A few quick tests that read the Town Centre calibration and annotations (no models).
DATA_TESTS = "tests/pose/test_towncentre.py::test_parsed_values"


def run_data_test(data_dir: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "POSEMETRY_TEST_DATA_DIR": str(data_dir)}
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:randomly", "-rs", DATA_TESTS]
    return subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)


def test_the_data_folder_can_be_anywhere(tmp_path: Path) -> None:
    real = require_dir(TOWN_CENTRE, "Town Centre data")
    elsewhere = tmp_path / "somewhere" / "data"
    elsewhere.mkdir(parents=True)
    (elsewhere / "oxford_town_centre").symlink_to(real)
    found = run_data_test(elsewhere)
    assert found.returncode == 0 and "1 passed" in found.stdout, found.stdout + found.stderr


def test_a_missing_folder_skips_naming_it_and_the_setting(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.support import shared

    monkeypatch.setenv("POSEMETRY_TEST_DATA_DIR", str(tmp_path / "empty"))
    with pytest.raises(pytest.skip.Exception) as skipped:
        require_dir(shared.data_dir_path() / "oxford_town_centre", "Town Centre data")
    assert str(tmp_path / "empty" / "oxford_town_centre") in str(skipped.value)
    assert "POSEMETRY_TEST_DATA_DIR" in str(skipped.value)


@pytest.mark.parametrize("value", ["", None])
def test_unset_means_the_checkouts_sibling(value: str | None, monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.support import shared

    if value is None:
        monkeypatch.delenv("POSEMETRY_TEST_DATA_DIR", raising=False)
    else:
        monkeypatch.setenv("POSEMETRY_TEST_DATA_DIR", value)
    assert shared.data_dir_path() == REPO.parent / "shared" / "data"
