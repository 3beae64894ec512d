"""`posemetry bench pose` harness on one real frame: each detector plan timed, the split and the report printable."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from bench.pose import pose_lines, run_pose_benchmark


def test_pose_benchmark_on_one_frame(model_dir: Path, town_dir: Path, tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    shutil.copyfile(town_dir / "frames" / "clip_000060.jpg", frames / "clip_000060.jpg")
    shutil.copyfile(town_dir / "TownCentre-calibration-ci.txt", tmp_path / "TownCentre-calibration-ci.txt")
    messages: list[str] = []
    result = run_pose_benchmark(model_dir, frames, ("auto",), repeats=1, progress=messages.append)
    assert [t.plan for t in result.timings] == ["uncalibrated", "later", "calibrated"]
    assert messages
    for timing in result.timings:
        assert len(timing.wall_s) == 1 and timing.people[0] >= 5
        stages = sum(timing.stage_wall_s[stage][0] for stage in ("detector", "tiling", "pose"))
        assert 0 < stages <= timing.wall_s[0]
        assert timing.cpu_s[0] > 0 and timing.stage_cpu_s["detector"][0] > 0
        assert timing.input_pixels[0] > 640 * 384  # more than the plain pass: the plan's other regions
        assert 0 <= timing.thunder_people[0] <= timing.people[0]
        assert 0 <= timing.reread_people[0] <= timing.people[0]
    lines = pose_lines(result)
    assert any("auto" in line and "calibrated" in line and "<= 100 ms" in line for line in lines)


def test_pose_benchmark_times_each_runtime(model_dir: Path, town_dir: Path, tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    shutil.copyfile(town_dir / "frames" / "clip_000060.jpg", frames / "clip_000060.jpg")
    result = run_pose_benchmark(
        model_dir, frames, ("lightning",), repeats=1, plans=("uncalibrated",), runtimes=("onnxruntime", "openvino")
    )
    assert [t.runtime for t in result.timings] == ["onnxruntime", "openvino"]
    # The same detector (onnxruntime in float32 for both), so the same people.
    assert result.timings[0].people == result.timings[1].people
    assert any(" openvino " in line for line in pose_lines(result))


def test_missing_frames_are_an_error(model_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="clip_"):
        run_pose_benchmark(model_dir, tmp_path, ("lightning",), repeats=1)
