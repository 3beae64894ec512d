"""A person partly hidden behind a nearer one gets their own pose (service/pose/occlusion.py, real inference).

Town Centre frames 48 and 54: a woman in a dark coat walks right behind the woman in red, whose head and body
cover her from the chest down. MoveNet SinglePose reads one pose per crop, and the hidden woman's square crop holds
the woman in red too: on frame 48 it read the woman in red (a `same pose as person N` copy, neither placed nor
evidence), on frame 54 it found no confident shoulders. With the woman in red masked out of her crop she is read
from her own head and shoulders, placed from them (her lower body hidden), and is no copy.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.towncentre import as_calibration, load_calibration
from service.frames.keypoints import PARTIAL_REASON, people_from_detections
from service.pose.pipeline import TopDownPose
from service.pose.types import DetectedPerson

from .conftest import IMAGE_SIZE

HIDDEN_NECK = {48: (1745.0, 765.0), 54: (1732.0, 775.0)}
"""Frame -> a pixel on the hidden woman's neck, above the woman in red's head (px)."""
RED_CHEST = {48: (1705.0, 900.0), 54: (1710.0, 905.0)}
"""Frame -> a pixel on the woman in red's chest (px)."""


def _box_holding(found: list[DetectedPerson], point: tuple[float, float], top_above: float) -> int:
    """The most confident person whose box holds the point and begins above `top_above`."""
    x, y = point
    holding = [
        k for k, p in enumerate(found) if p.box_xyxy_px[0] < x < p.box_xyxy_px[2] and p.box_xyxy_px[1] < top_above
    ]
    holding = [k for k in holding if found[k].box_xyxy_px[1] < y < found[k].box_xyxy_px[3]]
    assert holding, f"nobody boxed at {point}"
    return holding[0]


def _shoulders(person: DetectedPerson) -> np.ndarray:
    return np.asarray(person.keypoints_px[5:7], dtype=float).mean(axis=0)


@pytest.mark.parametrize("policy", ["uncalibrated", "calibrated"])
@pytest.mark.parametrize("frame", sorted(HIDDEN_NECK))
def test_the_woman_behind_the_woman_in_red_gets_her_own_shoulders(
    lightning: TopDownPose, town_dir: Path, frame: int, policy: str
) -> None:
    image = cv2.imread(str(town_dir / "frames" / f"clip_{frame:06d}.jpg"))
    assert image is not None
    calibration = None
    if policy == "calibrated":
        calibration = as_calibration(load_calibration(town_dir / "TownCentre-calibration-ci.txt"))
    found = lightning(image, calibration)
    hidden = _box_holding(found, HIDDEN_NECK[frame], HIDDEN_NECK[frame][1])
    red = _box_holding(found, RED_CHEST[frame], RED_CHEST[frame][1])
    assert hidden != red
    her, other = found[hidden], found[red]
    height_px = her.box_xyxy_px[3] - her.box_xyxy_px[1]
    # Her own shoulders: confident, below her neck point's row band and well above the woman in red's.
    assert (her.keypoint_scores[5:7] >= 0.3).all(), her.keypoint_scores[5:7]
    gap_px = float(np.hypot(*(_shoulders(her) - _shoulders(other))))
    assert gap_px > 0.15 * height_px, (frame, policy, _shoulders(her), _shoulders(other))
    assert _shoulders(her)[1] < other.box_xyxy_px[1], "her shoulders lie above the woman in red's box"
    assert _shoulders(her)[1] - her.box_xyxy_px[1] < 0.4 * height_px
    rows = people_from_detections(found, IMAGE_SIZE)
    assert not (rows[hidden].unusable_reason or "").startswith("same pose"), rows[hidden].unusable_reason
    # Placed from her shoulders (her legs are behind the woman in red), never from a box drawn to hidden feet.
    assert rows[hidden].shoulder_px is not None and rows[hidden].ankle_px is None
    assert rows[hidden].unusable_reason == PARTIAL_REASON


def test_without_the_mask_she_is_read_as_the_woman_in_red(model_dir: Path, town_dir: Path) -> None:
    """The premise: one reading per person (as before) gives frame 48's hidden woman the woman in red's pose."""
    image = cv2.imread(str(town_dir / "frames" / "clip_000048.jpg"))
    assert image is not None
    plain = TopDownPose(model_dir, "lightning", mask_nearer=False)
    found = plain(image)
    hidden = _box_holding(found, HIDDEN_NECK[48], HIDDEN_NECK[48][1])
    red = _box_holding(found, RED_CHEST[48], RED_CHEST[48][1])
    assert float(np.hypot(*(_shoulders(found[hidden]) - _shoulders(found[red])))) < 10
    rows = people_from_detections(found, IMAGE_SIZE)
    assert (rows[hidden].unusable_reason or "").startswith(f"same pose as person {red}")
    assert plain.last_times.reread_people == 0
