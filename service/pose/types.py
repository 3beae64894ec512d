"""What a pose model hands the rest of the service: people with COCO-17 keypoints, independent of the model.

Every runner (the two-stage RTMDet + MoveNet pipeline today, RTMO or RTMPose later) implements `PoseEstimator`,
so the inference worker, the offline `analyze` command and the benchmark never see a model's tensors.
Coordinates are image pixels of the frame that was passed in (origin top-left, x right, y down).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from service.domain import Posture

if TYPE_CHECKING:
    from service.geometry import Calibration

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
    keypoint_trusted: np.ndarray | None = None
    """(17,) bool: the keypoint was seen (score >= 0.3), is not inside the box of a person in front, and, for an
    ankle, hangs below a seen knee (service/pose/assess.py). None when the estimator did not assess its people:
    then a score of at least 0.3 is the only test."""
    posture: Posture = "unknown"
    """`standing` (shoulders and ankles trusted, legs extended: calibration evidence), `seated` (legs seen but
    folded: seated or crouching; a position from trusted ankles, else from the shoulders with a seated height),
    `partial` (shoulders trusted, lower body not: a position from the shoulders) or `unknown` (shoulders not
    trusted: not placed)."""
    pose_model: str = ""
    """Which pose model read this person (the pipeline picks Thunder or Lightning by the person's size)."""
    appearance: bytes | None = None
    """What they look like (service.geometry.appearance: colour histograms of torso and legs, 128 bytes), for
    `standing` people: it lets calibration link one person across frames seconds apart. None for others, or when
    too little of the body was seen."""

    def coco_keypoints(self) -> list[list[float]]:
        """`[[x, y, score] x 17]`: the shape the keypoint API accepts and the store keeps."""
        points = zip(self.keypoints_px, self.keypoint_scores, strict=True)
        return [[float(x), float(y), float(score)] for (x, y), score in points]


class PoseEstimator(Protocol):
    """Image in, people out. Implementations load their sessions once and are reused across frames."""

    name: str
    """Short identifier recorded with results, e.g. `rtmdet-nano+movenet-thunder`."""

    def __call__(self, image_bgr: np.ndarray, calibration: Calibration | None = None) -> list[DetectedPerson]:
        """People in an (H, W, 3) uint8 BGR image (OpenCV's order), most confident detection first.

        `calibration`, the camera's current one when it has one, lets the estimator search where and at the scale
        people can appear; without it, the sizes of the people its first pass finds, or its fixed policy.
        """
        ...
