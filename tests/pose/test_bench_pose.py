"""`posemetry bench pose` harness on one real frame: both crop modes timed, the report printable."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from bench.pose import pose_lines, run_pose_benchmark


def test_pose_benchmark_on_one_frame(model_dir: Path, town_dir: Path, tmp_path: Path) -> None:
    shutil.copyfile(town_dir / "frames" / "clip_000060.jpg", tmp_path / "clip_000060.jpg")
    messages: list[str] = []
    result = run_pose_benchmark(model_dir, tmp_path, ("lightning",), repeats=1, progress=messages.append)
    assert [(t.pose_model, t.mode) for t in result.timings] == [("lightning", "concurrent"), ("lightning", "loop")]
    assert messages
    for timing in result.timings:
        assert len(timing.total_s) == 1 and timing.people[0] >= 5
        assert timing.detector_s[0] + timing.pose_s[0] <= timing.total_s[0]
        assert timing.cpu_s[0] > 0
    lines = pose_lines(result)
    assert any("lightning" in line and "concurrent" in line for line in lines)
    assert any("<= 80 ms" in line for line in lines)


def test_missing_frames_are_an_error(model_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="clip_"):
        run_pose_benchmark(model_dir, tmp_path, ("lightning",), repeats=1)
