"""A worker's start with the pose queue: no pose models at all is a keypoint-only deployment (one INFO line), a
broken install is an ERROR that names the fix."""

from __future__ import annotations

import io
from pathlib import Path

from service.pose.model_files import DETECTOR
from service.settings import Settings
from tests.support.logs import json_lines
from workers.jobs import preload_pose


def test_no_models_at_all_is_info_not_error(tmp_path: Path, json_log: io.StringIO) -> None:
    preload_pose(Settings(model_dir=tmp_path / "never-fetched", data_dir=tmp_path))
    lines = [line for line in json_lines(json_log) if line["logger"] == "workers.jobs"]
    assert [line["level"] for line in lines] == ["INFO"], lines
    message = lines[0]["message"]
    assert "keypoint frames are unaffected" in message and "posemetry models fetch --dir" in message


def test_a_broken_install_is_an_error(tmp_path: Path, json_log: io.StringIO) -> None:
    (tmp_path / DETECTOR.file_name).write_bytes(b"truncated")
    preload_pose(Settings(model_dir=tmp_path, data_dir=tmp_path))
    lines = [line for line in json_lines(json_log) if line["logger"] == "workers.jobs"]
    assert [line["level"] for line in lines] == ["ERROR"], lines
    assert "corrupt" in lines[0]["message"] and "posemetry models fetch --dir" in lines[0]["message"]
