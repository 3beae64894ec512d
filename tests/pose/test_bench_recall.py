"""`posemetry bench recall` harness on a few real frames: the matching rules and a printable report."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.recall import CLIP_VIDEO, match_town, other_clip_frames, recall_lines, run_recall_benchmark, town_truth
from bench.towncentre import Annotation

from .test_atrium import ANNOTATION


def test_town_matching_allows_the_annotation_lag_and_visible_parts() -> None:
    annotations = {
        10: [Annotation(1, (120.0, 100.0, 140.0, 120.0), (100.0, 100.0, 160.0, 300.0))],
        6: [Annotation(1, None, (60.0, 100.0, 120.0, 300.0))],
    }
    people = town_truth(annotations, 10)
    assert len(people) == 1 and len(people[0].lagged) == 2
    strict, visible = match_town(people, np.array([[62.0, 100.0, 121.0, 300.0]]))  # where they were 4 frames ago
    assert strict.all() and visible.all()
    strict, visible = match_town(people, np.array([[102.0, 98.0, 158.0, 190.0]]))  # upper body (legs hidden)
    assert not strict.any() and visible.all()
    strict, visible = match_town(people, np.array([[300.0, 100.0, 360.0, 300.0]]))
    assert not strict.any() and not visible.any()


def test_recall_benchmark_on_a_few_frames(model_dir: Path, town_dir: Path, atrium_dir: Path, tmp_path: Path) -> None:
    town = tmp_path / "town"
    (town / "frames").mkdir(parents=True)
    for name in ("clip_000000.jpg", "clip_000054.jpg"):
        shutil.copyfile(town_dir / "frames" / name, town / "frames" / name)
    for name in ("TownCentre-groundtruth.top", "TownCentre-calibration-ci.txt"):
        shutil.copyfile(town_dir / name, town / name)
    atrium = tmp_path / "atrium"
    atrium.mkdir()
    shutil.copyfile(atrium_dir / "frame_49650.jpg", atrium / "frame_49650.jpg")
    result = run_recall_benchmark(model_dir, town, atrium, ANNOTATION, ("plain", "later", "calibrated"))
    plain, later, calibrated = result.results
    assert plain.town.frames == 2 and plain.town.recall()[1] >= 15
    assert plain.town.recall()[0] >= 0.8 * plain.town.recall()[1]
    # The second frame sized by the first one's people: bands beyond the plain pass, and no fewer people found.
    assert later.town.pixels[1] > plain.town.pixels[1] and later.town.recall()[0] >= plain.town.recall()[0]
    assert plain.atrium_hits["standing"][1] == 10 and not calibrated.atrium_found  # no atrium calibration given
    assert plain.clip.frames == 0  # no clip video in this folder
    lines = recall_lines(result)
    assert any(line.strip().startswith("plain") and "%" in line for line in lines)
    assert any("--atrium-calibration" in line for line in lines)
    assert not any("other frames of the clip" in line for line in lines)

    (town / CLIP_VIDEO).symlink_to(town_dir / CLIP_VIDEO)
    result = run_recall_benchmark(model_dir, town, atrium, ANNOTATION, ("uncalibrated",), clip_frames=2)
    (uncalibrated,) = result.results
    assert uncalibrated.town.frames == 2 and uncalibrated.clip.frames == 2
    assert uncalibrated.clip.recall()[1] >= 15 and uncalibrated.clip.recall()[0] >= 0.9 * uncalibrated.clip.recall()[1]
    lines = recall_lines(result)
    assert any("2 other frames of the clip" in line for line in lines)
    with pytest.raises(FileNotFoundError):
        run_recall_benchmark(model_dir, tmp_path / "none", atrium, ANNOTATION, ("plain",))


def test_the_other_clip_frames_are_spread_over_the_clip_and_skip_the_chosen_ones(town_dir: Path) -> None:
    video = town_dir / CLIP_VIDEO
    skip = set(range(0, 126, 6)) | {125}
    every = [number for number, _ in other_clip_frames(video, skip)]
    assert len(every) == 126 - len(skip) and not skip & set(every) and every == sorted(every)
    three = list(other_clip_frames(video, skip, 3))
    assert [number for number, _ in three] == [1, 63, 124]  # the first, the middle and the last of the 104
    assert all(image.shape == (1080, 1920, 3) for _, image in three)
    # The frames are the clip's: frame 1 is within JPEG noise of its neighbour, the stored frame 0.
    first = cv2.imread(str(town_dir / "frames" / "clip_000000.jpg")).astype(float)
    assert np.abs(three[0][1] - first).mean() < np.abs(three[1][1] - first).mean()
    assert list(other_clip_frames(video, skip, 0)) == [] and list(other_clip_frames(town_dir / "none.mp4", skip)) == []
