"""What a pose model hands the rest of the service: people with COCO-17 keypoints, independent of the model.

Every runner (the two-stage RTMDet + MoveNet pipeline today, RTMO or RTMPose later) implements `PoseEstimator`,
so the inference worker, the offline `analyze` command and the benchmark never see a model's tensors.
Coordinates are image pixels of the frame that was passed in (origin top-left, x right, y down).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

COCO17_KEYPOINTS = 17


@dataclass(frozen=True)
class DetectedPerson:
    """One person found in a frame."""

    box_xyxy_px: tuple[float, float, float, float]
    """Detector box: left, top, right, bottom."""
    detection_score: float
    """Detector confidence in [0, 1]."""
    keypoints_px: np.ndarray
    """(17, 2) x, y per COCO-17 keypoint, in the order nose, eyes, ears, shoulders, elbows, wrists, hips, knees,
    ankles (left before right; "left" is the person's own left)."""
    keypoint_scores: np.ndarray
    """(17,) confidence per keypoint in [0, 1]."""

    def coco_keypoints(self) -> list[list[float]]:
        """`[[x, y, score] x 17]`: the shape the keypoint API accepts and the store keeps."""
        points = zip(self.keypoints_px, self.keypoint_scores, strict=True)
        return [[float(x), float(y), float(score)] for (x, y), score in points]


class PoseEstimator(Protocol):
    """Image in, people out. Implementations load their sessions once and are reused across frames."""

    name: str
    """Short identifier recorded with results, e.g. `rtmdet-nano+movenet-thunder`."""

    def __call__(self, image_bgr: np.ndarray) -> list[DetectedPerson]:
        """People in an (H, W, 3) uint8 BGR image (OpenCV's order), most confident detection first."""
        ...
