"""The top-down pose estimator: RTMDet-nano finds people, MoveNet SinglePose reads each one's keypoints.

Top-down because the people a fixed surveillance camera sees are many and small: detector passes at the scales
that make people the detector's favourite size (regions.py) plus one small crop per person keeps every pedestrian
at the pose model's working resolution, where bottom-up or multi-person models (MoveNet MultiPose caps at 6
people) lose the far ones.

One call: plan the detector regions (bands guided by the camera's calibration; without one, bands sized by the people
a first pass found, or where they do not say, the fixed uncalibrated policy plus a second look around the people it
found too small), detect and merge (one box per person), read each person
with MoveNet (Thunder or Lightning by the person's size when `pose_model` is `auto`), then assess each person's
keypoints and posture against the others' boxes (assess.py: which keypoints are trustworthy, who stands). A person
partly hidden behind a nearer one whose reading is lost (the nearer person's pose, or no trusted shoulders) is read
again with the nearer people masked out of the crop, and keeps that reading when it is their own (occlusion.py).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache, partial
from pathlib import Path
from typing import TYPE_CHECKING, Final, Literal

import numpy as np

from .appearance import appearance_descriptor
from .assess import FRONT_MARGIN, Assessment, assess_frame
from .detector import DEFAULT_INPUT_PX, DEFAULT_SCORE_THRESHOLD, Detections, PersonDetector, RegionTimes
from .model_files import POSE_INPUT_PX, PoseChoice, resolve_choice
from .movenet import CropMode, MoveNet, PoseOutput, crop_window, extract_crop, read_people
from .occlusion import accept, needs_reading
from .regions import (
    UNCALIBRATED_SCALES,
    Region,
    calibrated_plan,
    observed_plan,
    plan_cost,
    sizes_from_people,
    standing_height_px,
    uncalibrated_plan,
    zoom_regions,
)
from .sessions import PoseRuntime, native_bf16, resolve_runtime, thread_pool
from .types import DetectedPerson

if TYPE_CHECKING:
    from service.geometry import Calibration
    from service.settings import Settings

_PLANS_KEPT: Final = 64
Sizing = Literal["calibration", "camera's people", "frame's people", "fixed passes"]


def _plan_key(
    image_size_px: tuple[int, int],
    calibration: Calibration | None,
    feet_box_px: tuple[float, float, float, float] | None,
) -> tuple[object, ...]:
    """What a detector plan depends on (regions.calibrated_plan reads no other field of the calibration)."""
    if calibration is None:
        return (tuple(image_size_px), feet_box_px)
    camera = (calibration.fx, calibration.fy, calibration.cx, calibration.cy, calibration.rho, calibration.height_m)
    return (tuple(image_size_px), feet_box_px, camera, tuple(calibration.normal), tuple(calibration.image_size))


THUNDER_FROM_CROP_PX: Final = 2 * POSE_INPUT_PX["lightning"]
"""`auto` reads a person with Thunder when their crop is at least this many pixels wide (Lightning would have to
halve it), else with Lightning, for a quarter of the CPU (~5 vs ~19 ms of one core per crop).

Measured against Town Centre's published camera (how far each person's shoulder centre lies from the vertical
through their ankle centre, and the spread of the shoulder heights that implies), on the 105 people both models
read confidently on all 22 clip frames: Lightning is as consistent as Thunder at every size (median lateral offset
2.0 vs 2.0 % of the height under 160 px, 2.3 vs 2.9 % for 205-260 px people), so Thunder is kept for the people
Lightning would see at half resolution or less. Below Thunder's own 256 px input the crop is upsampled for it:
Thunder then sees no pixel Lightning does not."""


@dataclass
class StageTimes:
    """Seconds spent per stage by the last call: the benchmark's detector / tiling / pose split.

    `detector` is the plain whole-frame pass (the frame letterboxed to `detector_input_px`), `tiling` every other
    region of the plan plus merging the regions' boxes, `pose` cropping, MoveNet and the assessment. Wall and
    CPU time (all threads) for each; detector regions run side by side overlap, so the detection's wall time is
    split between `detector` and `tiling` in proportion to their CPU.
    """

    detector_s: float = 0.0
    tiling_s: float = 0.0
    pose_s: float = 0.0
    detector_cpu_s: float = 0.0
    tiling_cpu_s: float = 0.0
    pose_cpu_s: float = 0.0
    people: int = 0
    regions: int = 0
    input_pixels: int = 0
    """Detector input pixels of the plan."""
    thunder_people: int = 0
    reread_people: int = 0
    """People read a second time with the nearer people masked out of their crop (occlusion.py)."""
    reread_kept: int = 0
    """Of those, the ones whose masked reading was kept."""


@dataclass
class TopDownPose:
    """`PoseEstimator` over verified model files; sessions are created once per instance and reused across frames."""

    model_dir: Path
    pose_model: PoseChoice = "auto"
    detector_input_px: int = DEFAULT_INPUT_PX
    """Side of the plain whole-frame detector pass (the first pass of every plan)."""
    score_threshold: float = DEFAULT_SCORE_THRESHOLD
    threads: int | None = None
    crops: CropMode = "concurrent"
    """How a frame's person crops run (movenet.py): `concurrent` (default, one crop per core at a time), `loop`
    (one after another, each on all threads: the plain baseline) or `batched` (split graph; no faster on CPU)."""
    uncalibrated_scales: tuple[float, ...] = UNCALIBRATED_SCALES
    """Whole-frame passes without a calibration (regions.uncalibrated_plan); the first is `detector_input_px`."""
    pose_runtime: PoseRuntime = "auto"
    """What MoveNet runs on (sessions.py): `auto` is OpenVINO in bfloat16 where the CPU has it natively, else
    onnxruntime in float32. The detector always runs on onnxruntime in float32."""
    mask_nearer: bool = True
    """Read a partly hidden person whose reading is lost again with the nearer people masked out (occlusion.py);
    False: one reading per person, as before (the benchmark's baseline)."""
    name: str = field(init=False)
    last_times: StageTimes = field(init=False, default_factory=StageTimes)
    last_plan: list[Region] = field(init=False, default_factory=list)
    last_sizing: Sizing = field(init=False, default="fixed passes")
    """What sized the last frame's search (`detect`): its log line says so."""
    _plans: dict[tuple[object, ...], list[Region]] = field(init=False, default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        paths = resolve_choice(self.model_dir, self.pose_model)
        self.detector = PersonDetector(
            paths[0].detector,
            input_px=self.detector_input_px,
            score_threshold=self.score_threshold,
            threads=self.threads,
        )
        runtime = resolve_runtime(self.pose_runtime)
        self.movenets = {
            path.pose_model: MoveNet(
                path.pose, path.pose_model, threads=self.threads, crops=self.crops, runtime=runtime
            )
            for path in paths
        }
        # Recorded with every result: which keypoints these are, down to the arithmetic that produced them.
        precision = "@bf16" if runtime == "openvino" and native_bf16() else ""
        self.name = f"rtmdet-nano@{self.detector_input_px}+movenet-{self.pose_model}{precision}"

    def plan(
        self,
        image_size_px: tuple[int, int],
        calibration: Calibration | None = None,
        feet_box_px: tuple[float, float, float, float] | None = None,
    ) -> list[Region]:
        """The detector regions for a frame of this size: the plain pass, then the policy's or the calibration's.

        A plan depends only on the camera, so it is kept (_PLANS_KEPT of them, least recently used out): a worker
        sees a few cameras' frames over and over, and a guided plan costs ~5 ms of the frame's critical path."""
        key = _plan_key(image_size_px, calibration, feet_box_px)
        plan = self._plans.pop(key, None)
        if plan is None:
            plan = uncalibrated_plan(image_size_px, self.uncalibrated_scales[:1], base_input_px=self.detector_input_px)
            if calibration is None:
                plan += uncalibrated_plan(image_size_px, self.uncalibrated_scales[1:])
            else:
                plan += calibrated_plan(calibration, image_size_px, feet_box_px=feet_box_px)
            while len(self._plans) >= _PLANS_KEPT:
                del self._plans[next(iter(self._plans))]
        self._plans[key] = plan
        return list(plan)

    def __call__(
        self,
        image_bgr: np.ndarray,
        calibration: Calibration | None = None,
        *,
        feet_box_px: tuple[float, float, float, float] | None = None,
        seen_boxes_px: np.ndarray | None = None,
    ) -> list[DetectedPerson]:
        """People in an (H, W, 3) uint8 BGR image, most confident detection first.

        `calibration` (the camera's current one) guides the detector (regions.calibrated_plan); `feet_box_px`
        limits that search to where the camera's people have been seen standing. Without a calibration,
        `seen_boxes_px` (the boxes of whole standing people the camera's recent frames found) sizes the search
        when they determine the sizes, else the frame's own first pass does (`detect`).
        """
        image = np.asarray(image_bgr)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected an (H, W, 3) uint8 BGR image, got {image.shape} {image.dtype}")
        detections, times = self.detect(image, calibration, feet_box_px, seen_boxes_px)
        start, start_cpu = time.perf_counter(), time.process_time()
        boxes = detections.boxes_xyxy_px
        models = self._models_for(boxes)
        poses = read_people(image, boxes, [self.movenets[model] for model in models])
        assessments = assess_frame(boxes, poses.keypoints_px, poses.scores, image.shape[0])
        reread = kept = 0
        if self.mask_nearer:
            poses, reread, kept = self._read_hidden(image, boxes, models, poses, assessments)
            if kept:
                assessments = assess_frame(boxes, poses.keypoints_px, poses.scores, image.shape[0])
        # Descriptors for the calibration evidence only, side by side (OpenCV releases the interpreter's lock).
        standing = [k for k, assessment in enumerate(assessments) if assessment.posture == "standing"]
        described = thread_pool(self.detector.workers).map(lambda k: _appearance(image, boxes, k, poses), standing)
        appearances: list[bytes | None] = [None] * len(boxes)
        for k, descriptor in zip(standing, described, strict=True):
            appearances[k] = descriptor
        self.last_times = self._stage_times(times, time.perf_counter() - start, time.process_time() - start_cpu)
        self.last_times.people = len(boxes)
        self.last_times.reread_people, self.last_times.reread_kept = reread, kept
        self.last_times.thunder_people = models.count("thunder")
        return [
            DetectedPerson(
                box_xyxy_px=(float(box[0]), float(box[1]), float(box[2]), float(box[3])),
                detection_score=float(score),
                keypoints_px=keypoints,
                keypoint_scores=scores,
                keypoint_trusted=assessment.trusted,
                posture=assessment.posture,
                pose_model=model,
                appearance=appearance,
            )
            for box, score, keypoints, scores, assessment, model, appearance in zip(
                boxes,
                detections.scores,
                poses.keypoints_px,
                poses.scores,
                assessments,
                models,
                appearances,
                strict=True,
            )
        ]

    def detect(
        self,
        image: np.ndarray,
        calibration: Calibration | None = None,
        feet_box_px: tuple[float, float, float, float] | None = None,
        seen_boxes_px: np.ndarray | None = None,
    ) -> tuple[Detections, RegionTimes]:
        """The detection stage alone: one box per person, and what each region cost (`last_plan` is the plan).

        Without a calibration, when the people the camera's recent frames found (`seen_boxes_px`) say how tall
        people appear at each row (regions.observed_plan), the plain pass and the bands they size run together, as
        a calibrated plan's do. Otherwise the plain pass runs first, and the people it found size the bands; where
        they do not either, the fixed policy's finer passes follow, then a second look around the people they found
        too small (regions.zoom_regions)."""
        height, width = image.shape[:2]
        size = (width, height)
        if calibration is not None:
            self.last_plan, self.last_sizing = self.plan(size, calibration, feet_box_px), "calibration"
            return self.detector.detect(image, self.last_plan, size_of=partial(standing_height_px, calibration))
        fixed = self.plan(size, None)
        plain = uncalibrated_plan(size, self.uncalibrated_scales[:1], base_input_px=self.detector_input_px)
        seen = None if seen_boxes_px is None else sizes_from_people(seen_boxes_px, size)
        bands = None if seen is None else observed_plan(seen, size)
        if seen is not None and bands is not None:
            self.last_plan, self.last_sizing = plain + bands, "camera's people"
            return self.detector.detect(image, self.last_plan, size_of=seen)
        found = self.detector.detect(image, plain)
        own = sizes_from_people(found[0].boxes_xyxy_px, size)
        bands = None if own is None else observed_plan(own, size)
        if own is not None and bands is not None:
            self.last_plan, self.last_sizing = plain + bands, "frame's people"
            return self.detector.detect(image, bands, found, size_of=own)
        detections, times = self.detector.detect(image, fixed[len(plain) :], found)
        self.last_plan, self.last_sizing = fixed, "fixed passes"
        zoom = zoom_regions(detections.boxes_xyxy_px, max(region.scale for region in fixed), (width, height))
        if zoom:
            detections, times = self.detector.detect(image, zoom, (detections, times))
            self.last_plan = self.last_plan + zoom
        return detections, times

    def _read_hidden(
        self,
        image: np.ndarray,
        boxes: np.ndarray,
        models: list[str],
        poses: PoseOutput,
        assessments: Sequence[Assessment],
    ) -> tuple[PoseOutput, int, int]:
        """The frame's poses with each lost hidden person read again, nearer people masked (occlusion.py); and
        how many were read again and how many of those readings were kept."""
        hidden = needs_reading(boxes, poses.keypoints_px, poses.scores, assessments)
        if not hidden:
            return poses, 0, 0
        keypoints, scores = poses.keypoints_px.copy(), poses.scores.copy()
        kept = 0
        for model in sorted({models[h.index] for h in hidden}):
            reader = self.movenets[model]
            mine = [h for h in hidden if models[h.index] == model]
            windows = [crop_window(boxes[h.index]) for h in mine]
            crops = [
                extract_crop(image, w, reader.input_px, boxes[h.nearer]) for h, w in zip(mine, windows, strict=True)
            ]
            raw = reader.infer(np.stack(crops))
            for h, window, reading in zip(mine, windows, raw, strict=True):
                new_keypoints, new_scores = window.to_image(reading[:, 1::-1]), reading[:, 2].astype(np.float64)
                if accept(h, new_keypoints, new_scores, boxes, poses.keypoints_px, poses.scores):
                    keypoints[h.index], scores[h.index] = new_keypoints, new_scores
                    kept += 1
        return PoseOutput(keypoints_px=keypoints, scores=scores), len(hidden), kept

    def _models_for(self, boxes: np.ndarray) -> list[str]:
        """Which MoveNet reads each box: the configured one, or by crop size for `auto`."""
        if self.pose_model != "auto":
            return [self.pose_model] * len(boxes)
        return ["thunder" if crop_window(box).side >= THUNDER_FROM_CROP_PX else "lightning" for box in boxes]

    def _stage_times(self, times: RegionTimes, pose_s: float, pose_cpu_s: float) -> StageTimes:
        base = times.base
        detector_cpu_s = times.cpu_s[base] if base is not None else 0.0
        # Regions run side by side share the wall clock: it is split between the stages as their CPU is.
        detector_s = times.elapsed_s * detector_cpu_s / sum(times.cpu_s) if sum(times.cpu_s) > 0 else 0.0
        return StageTimes(
            detector_s=detector_s,
            tiling_s=times.elapsed_s - detector_s,
            pose_s=pose_s,
            detector_cpu_s=detector_cpu_s,
            tiling_cpu_s=sum(times.cpu_s) - detector_cpu_s,
            pose_cpu_s=pose_cpu_s,
            regions=len(times.regions),
            input_pixels=plan_cost(times.regions),
        )


@lru_cache(maxsize=4)
def _cached_estimator(
    model_dir: Path, pose_model: PoseChoice, detector_input_px: int, threads: int | None, pose_runtime: PoseRuntime
) -> TopDownPose:
    return TopDownPose(
        model_dir, pose_model, detector_input_px=detector_input_px, threads=threads, pose_runtime=pose_runtime
    )


def load_pose_estimator(settings: Settings) -> TopDownPose:
    """The process's estimator for these settings, built on first use (sessions and file checks cost ~0.5 s)."""
    return _cached_estimator(
        Path(settings.model_dir).expanduser().resolve(),
        settings.pose_model,
        settings.detector_input_px,
        settings.inference_threads,
        settings.pose_runtime,
    )


def _appearance(image: np.ndarray, boxes: np.ndarray, index: int, poses: PoseOutput) -> bytes | None:
    """Person `index`'s appearance descriptor, leaving out the boxes of the people in front of them (assess.py's
    rule: a box reaching lower in the frame by FRONT_MARGIN of their height)."""
    box = boxes[index]
    front = boxes[:, 3] >= box[3] + FRONT_MARGIN * (box[3] - box[1])
    front[index] = False
    return appearance_descriptor(image, poses.keypoints_px[index], poses.scores[index], box, boxes[front])
