"""Pose-pipeline fixtures: the real model files and the Oxford Town Centre frames, one estimator per session.

The model directory comes from POSEMETRY_MODEL_DIR (what the service reads too), defaulting to the checkout's
sibling `../shared/models`; data from POSEMETRY_TEST_DATA_DIR, defaulting to `../shared/data` (tests.support.shared).
Tests that need them skip, naming the missing directory, only when the directory is absent; a directory that is
present but holds bad files fails loudly instead.
Building an estimator costs ~0.5 s, so each model's estimator is shared by the whole session.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from service.pose.pipeline import TopDownPose
from tests.support.shared import SHARED_DATA, TOWN_CENTRE, model_dir_path

TOWN = TOWN_CENTRE
ATRIUM = SHARED_DATA / "mot3d_atrium" / "frames"
IMAGE_SIZE = (1920, 1080)

# A standing person ~200 px tall: COCO-17 keypoints (x, y) from head to ankles.
POSE = np.array(
    [
        [500, 310],
        [495, 305],
        [505, 305],
        [490, 308],
        [510, 308],
        [480, 340],
        [520, 340],
        [475, 390],
        [525, 390],
        [472, 430],
        [528, 430],
        [488, 430],
        [512, 430],
        [490, 470],
        [510, 470],
        [491, 505],
        [509, 505],
    ],
    dtype=float,
)
# A few spread-out clip frames: enough people (9-14 annotated each) for recall, fast enough for CI.
TEST_FRAMES = (0, 30, 60, 90, 120)


@pytest.fixture(scope="session")
def model_dir() -> Path:
    path = model_dir_path()
    if not path.is_dir():
        pytest.skip(f"pose model directory {path} is absent (set POSEMETRY_MODEL_DIR or provide ../shared/models)")
    return path


@pytest.fixture(scope="session")
def town_dir() -> Path:
    if not TOWN.is_dir():
        pytest.skip(
            f"Oxford Town Centre data directory {TOWN} is absent (set POSEMETRY_TEST_DATA_DIR or ../shared/data)"
        )
    return TOWN


@pytest.fixture(scope="session")
def atrium_dir() -> Path:
    if not ATRIUM.is_dir():
        pytest.skip(f"atrium frames directory {ATRIUM} is absent (../shared/data/mot3d_atrium/frames)")
    return ATRIUM


def frame_number(path: Path) -> int:
    match = re.search(r"clip_(\d+)", path.name)
    assert match, path
    return int(match.group(1))


@pytest.fixture(scope="session")
def town_frames(town_dir: Path) -> dict[int, np.ndarray]:
    """frame number -> BGR image for TEST_FRAMES."""
    frames = {}
    for number in TEST_FRAMES:
        path = town_dir / "frames" / f"clip_{number:06d}.jpg"
        image = cv2.imread(str(path))
        assert image is not None, f"cannot read {path}"
        frames[number] = image
    return frames


@pytest.fixture(scope="session")
def thunder(model_dir: Path) -> TopDownPose:
    return TopDownPose(model_dir, "thunder")


@pytest.fixture(scope="session")
def lightning(model_dir: Path) -> TopDownPose:
    return TopDownPose(model_dir, "lightning")
