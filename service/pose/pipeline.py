"""The top-down pose estimator: RTMDet-nano finds people, MoveNet SinglePose reads each one's keypoints.

Top-down because the people a fixed surveillance camera sees are many and small: one detector pass at 640 px
plus one small crop per person keeps every pedestrian at the pose model's working resolution, where bottom-up or
multi-person models (MoveNet MultiPose caps at 6 people) lose the far ones.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .detector import DEFAULT_INPUT_PX, DEFAULT_SCORE_THRESHOLD, PersonDetector
from .model_files import PoseModelName, resolve_models
from .movenet import CropMode, MoveNet
from .types import DetectedPerson

if TYPE_CHECKING:
    from service.settings import Settings


@dataclass
class StageTimes:
    """Seconds spent per stage by the last call (the benchmark's detector vs pose split)."""

    detector_s: float = 0.0
    pose_s: float = 0.0
    people: int = 0


@dataclass
class TopDownPose:
    """`PoseEstimator` over verified model files; sessions are created once per instance and reused across frames."""

    model_dir: Path
    pose_model: PoseModelName = "thunder"
    detector_input_px: int = DEFAULT_INPUT_PX
    score_threshold: float = DEFAULT_SCORE_THRESHOLD
    threads: int | None = None
    crops: CropMode = "concurrent"
    """How a frame's person crops run (movenet.py): `concurrent` (default, one crop per core at a time), `loop`
    (one after another, each on all threads: the plain baseline) or `batched` (split graph; no faster on CPU)."""
    square_detector_input: bool = False
    """Pad the detector input to a square instead of to its stride (slower; see detector.letterbox)."""
    name: str = field(init=False)
    last_times: StageTimes = field(init=False, default_factory=StageTimes)

    def __post_init__(self) -> None:
        paths = resolve_models(self.model_dir, self.pose_model)
        self.detector = PersonDetector(
            paths.detector,
            input_px=self.detector_input_px,
            score_threshold=self.score_threshold,
            threads=self.threads,
            square=self.square_detector_input,
        )
        self.movenet = MoveNet(paths.pose, self.pose_model, threads=self.threads, crops=self.crops)
        self.name = f"rtmdet-nano@{self.detector_input_px}+movenet-{self.pose_model}"

    def __call__(self, image_bgr: np.ndarray) -> list[DetectedPerson]:
        """People in an (H, W, 3) uint8 BGR image, most confident detection first."""
        image = np.asarray(image_bgr)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected an (H, W, 3) uint8 BGR image, got {image.shape} {image.dtype}")
        start = time.perf_counter()
        detections = self.detector(image)
        detected = time.perf_counter()
        poses = self.movenet(image, detections.boxes_xyxy_px)
        self.last_times = StageTimes(detected - start, time.perf_counter() - detected, len(detections.scores))
        return [
            DetectedPerson(
                box_xyxy_px=(float(box[0]), float(box[1]), float(box[2]), float(box[3])),
                detection_score=float(score),
                keypoints_px=keypoints,
                keypoint_scores=scores,
            )
            for box, score, keypoints, scores in zip(
                detections.boxes_xyxy_px, detections.scores, poses.keypoints_px, poses.scores, strict=True
            )
        ]


@lru_cache(maxsize=4)
def _cached_estimator(
    model_dir: Path, pose_model: PoseModelName, detector_input_px: int, threads: int | None
) -> TopDownPose:
    return TopDownPose(model_dir, pose_model, detector_input_px=detector_input_px, threads=threads)


def load_pose_estimator(settings: Settings) -> TopDownPose:
    """The process's estimator for these settings, built on first use (sessions and file checks cost ~0.5 s)."""
    return _cached_estimator(
        Path(settings.model_dir).expanduser().resolve(),
        settings.pose_model,
        settings.detector_input_px,
        settings.inference_threads,
    )
