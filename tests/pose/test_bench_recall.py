"""`posemetry bench recall` harness on a few real frames: the matching rules and a printable report."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from bench.recall import match_town, recall_lines, run_recall_benchmark, town_truth
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
    assert plain.town_frames == 2 and plain.town_recall()[1] >= 15
    assert plain.town_recall()[0] >= 0.8 * plain.town_recall()[1]
    # The second frame sized by the first one's people: bands beyond the plain pass, and no fewer people found.
    assert later.town_pixels[1] > plain.town_pixels[1] and later.town_recall()[0] >= plain.town_recall()[0]
    assert plain.atrium_hits["standing"][1] == 10 and not calibrated.atrium_found  # no atrium calibration given
    lines = recall_lines(result)
    assert any(line.strip().startswith("plain") and "%" in line for line in lines)
    assert any("--atrium-calibration" in line for line in lines)
    with pytest.raises(FileNotFoundError):
        run_recall_benchmark(model_dir, tmp_path / "none", atrium, ANNOTATION, ("plain",))
