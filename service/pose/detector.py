"""RTMDet-nano person detector: letterboxed frame in, person boxes in image pixels out.

The exported graph already contains NMS and returns `dets` (x1, y1, x2, y2, score in input-tensor pixels) and
`labels` (always 0, person). Preprocessing follows mmdet's RTMDet convention exactly (BGR, letterbox in the
top-left corner, pad 114, per-channel mean/std), because any deviation costs recall on the small, far people a
surveillance camera mostly sees. The native size is 320, but 640 finds distant pedestrians the 320 input misses.

`PersonDetector.detect` runs a plan of regions (regions.py: parts of the frame, each at its own scale) and merges
their boxes into one per person (merge.py); calling the detector runs the single whole-frame letterbox.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import cv2
import numpy as np

from .merge import VOTE_FLOOR, merge_boxes
from .regions import STRIDE_PX, Region, SizeOf, ceil_to
from .sessions import Session, default_threads, make_session, thread_pool

DEFAULT_INPUT_PX: Final = 640
DEFAULT_SCORE_THRESHOLD: Final = 0.3
PAD_VALUE: Final = 114
MEAN_BGR: Final = np.array([103.53, 116.28, 123.675], dtype=np.float32)
STD_BGR: Final = np.array([57.375, 57.12, 58.395], dtype=np.float32)
_SCALE: Final = (1.0 / STD_BGR).astype(np.float32)
_OFFSET: Final = (-MEAN_BGR / STD_BGR).astype(np.float32)
_PAD_NORMALISED: Final = ((PAD_VALUE - MEAN_BGR) / STD_BGR).astype(np.float32)


@dataclass(frozen=True)
class Letterbox:
    """How an image was placed in the square input: scaled by `ratio`, top-left aligned, padded to `size_px`."""

    ratio: float
    size_px: int

    def to_image(self, xy_input: np.ndarray) -> np.ndarray:
        """Input-tensor pixel coordinates (..., 2k) back to image pixels (top-left placement: a pure scale)."""
        return np.asarray(xy_input, dtype=np.float64) / self.ratio

    def to_input(self, xy_image: np.ndarray) -> np.ndarray:
        """Image pixel coordinates to input-tensor pixels (the inverse of `to_image`)."""
        return np.asarray(xy_image, dtype=np.float64) * self.ratio


def letterbox(image_bgr: np.ndarray, size_px: int, *, square: bool = True) -> tuple[np.ndarray, Letterbox]:
    """(1, 3, H, W) float32 normalised input and the placement, for an (H, W, 3) uint8 BGR image.

    The longer side is scaled to `size_px`. `square` pads the other side to `size_px` too (mmdet's test-time
    `Pad(size=...)`); otherwise it is padded only to the network stride (mmdet's batch `size_divisor=32`), which
    for a 16:9 frame at 640 is a 640 x 384 input: 40 % less detector work, the same people found (the extra rows
    were pure padding; measured box differences in `tests/pose/test_pipeline.py`). The pad value 114 is normalised
    like the pixels (mmdet pads before normalising). Normalisation runs in float32 on the resized image only, as
    one multiply-add per channel written straight into the NCHW tensor: no float copy of the 1080p frame, no
    separate transpose.
    """
    height, width = image_bgr.shape[:2]
    ratio = size_px / max(height, width)
    new_w, new_h = max(1, round(width * ratio)), max(1, round(height * ratio))
    padded = (size_px, size_px) if square else (ceil_to(new_w, STRIDE_PX), ceil_to(new_h, STRIDE_PX))
    return _normalised(image_bgr, (new_w, new_h), padded, ratio), Letterbox(ratio=ratio, size_px=size_px)


def region_tensor(image_bgr: np.ndarray, region: Region) -> np.ndarray:
    """(1, 3, H, W) float32 normalised input for one region: its pixels resized by its scale, padded to the stride.

    A whole-frame region at scale S / longer side is exactly the stride-padded letterbox at S.
    """
    new_w, new_h = region.input_size
    padded = (ceil_to(new_w, STRIDE_PX), ceil_to(new_h, STRIDE_PX))
    return _normalised(image_bgr[region.y0 : region.y1, region.x0 : region.x1], (new_w, new_h), padded, region.scale)


def _normalised(image_bgr: np.ndarray, size: tuple[int, int], padded: tuple[int, int], ratio: float) -> np.ndarray:
    """The image resized to `size` (w, h), normalised into the top-left of a `padded` (w, h) tensor of pad value."""
    new_w, new_h = size
    interpolation = cv2.INTER_AREA if ratio < 1 else cv2.INTER_LINEAR
    resized = cv2.resize(image_bgr, (new_w, new_h), interpolation=interpolation)
    tensor = np.empty((1, 3, padded[1], padded[0]), dtype=np.float32)
    body = tensor[0, :, :new_h, :new_w]
    np.multiply(resized.transpose(2, 0, 1), _SCALE[:, None, None], out=body, casting="unsafe")
    body += _OFFSET[:, None, None]
    tensor[0, :, new_h:, :] = _PAD_NORMALISED[:, None, None]
    tensor[0, :, :new_h, new_w:] = _PAD_NORMALISED[:, None, None]
    return tensor


@dataclass(frozen=True)
class Detections:
    """Person boxes of one image, most confident first."""

    boxes_xyxy_px: np.ndarray
    """(N, 4) float64 left, top, right, bottom in image pixels, clipped to the image."""
    scores: np.ndarray
    """(N,) float64 in [0, 1]."""


@dataclass
class RegionTimes:
    """What one `detect` call spent, per region: the benchmark's detector/tiling split."""

    regions: list[Region] = field(default_factory=list)
    wall_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    """CPU time per region (all its threads): preprocessing, the session run and decoding."""
    merge_s: float = 0.0
    elapsed_s: float = 0.0
    """Wall time of the detect call(s) in all: regions run side by side overlap, so their walls add up to more."""
    found: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    """Per region, the (boxes, scores) it owns above the vote floor: the votes merge.py fuses (a second look adds
    its own to an earlier call's)."""

    @property
    def base(self) -> int | None:
        """Index of the plain detector pass (the first whole-frame region), None when the plan has none."""
        return next((k for k, r in enumerate(self.regions) if r.whole_frame and r.shared_edges == (False,) * 4), None)


class PersonDetector:
    """RTMDet-nano on one frame at a time (the session is created once and reused)."""

    def __init__(
        self,
        model_path: Path,
        *,
        input_px: int = DEFAULT_INPUT_PX,
        score_threshold: float = DEFAULT_SCORE_THRESHOLD,
        threads: int | None = None,
        square: bool = False,
    ) -> None:
        if input_px < STRIDE_PX or input_px % STRIDE_PX:
            raise ValueError(f"detector input must be a positive multiple of 32 px (its stride), got {input_px}")
        self.input_px = input_px
        self.score_threshold = score_threshold
        self.square = square
        """Pad the input to a square (mmdet's test pipeline) rather than to the stride: ~1.6x slower at 16:9."""
        self.workers = threads or default_threads()
        self.session = make_session(model_path, self.workers)
        # For regions run side by side, one core each (`detect`). onnxruntime's CPU kernels give the same boxes on
        # one thread as on several (a test compares), so the schedule never changes an answer.
        self.single = make_session(model_path, 1) if self.workers > 1 else self.session
        self._input_name = self.session.get_inputs()[0].name

    def __call__(self, image_bgr: np.ndarray) -> Detections:
        tensor, placement = letterbox(image_bgr, self.input_px, square=self.square)
        dets = self.session.run(["dets"], {self._input_name: tensor})[0][0]
        return decode(dets, placement, image_bgr.shape[:2], self.score_threshold)

    def detect(
        self,
        image_bgr: np.ndarray,
        plan: Sequence[Region],
        earlier: tuple[Detections, RegionTimes] | None = None,
        size_of: SizeOf | None = None,
    ) -> tuple[Detections, RegionTimes]:
        """One box per person over a plan of regions (each region keeps the people it owns; then merge.py).

        `earlier`: what an earlier call on the same image found and spent, merged into this answer (a second look).
        `size_of`: how tall a standing person appears with their feet at each pixel, where known (merge.py, rule 4).
        """
        times = RegionTimes()
        if earlier is not None:
            times.regions += earlier[1].regions
            times.found += earlier[1].found
            times.wall_s += earlier[1].wall_s
            times.cpu_s += earlier[1].cpu_s
            times.merge_s += earlier[1].merge_s
            times.elapsed_s += earlier[1].elapsed_s
        start = time.perf_counter()
        alone, side_by_side = schedule(plan, self.workers)
        results = {k: self._run_region(image_bgr, plan[k], self.session, time.process_time) for k in alone}
        if side_by_side:
            runs = thread_pool(self.workers).map(
                lambda k: self._run_region(image_bgr, plan[k], self.single, time.thread_time), side_by_side
            )
            results.update(zip(side_by_side, runs, strict=True))
        for k, region in enumerate(plan):
            result = results[k]
            times.found.append((result.boxes, result.scores))
            times.regions.append(region)
            times.wall_s.append(result.wall_s)
            times.cpu_s.append(result.cpu_s)
        merge_start = time.perf_counter()
        merged_boxes, merged_scores = merge_boxes(
            np.concatenate([np.zeros((0, 4)), *(boxes for boxes, _ in times.found)]),
            np.concatenate([np.zeros(0), *(scores for _, scores in times.found)]),
            np.concatenate([np.zeros(0, dtype=int), *(np.full(len(s), k) for k, (_, s) in enumerate(times.found))]),
            threshold=self.score_threshold,
            size_of=size_of,
        )
        times.merge_s += time.perf_counter() - merge_start
        times.elapsed_s += time.perf_counter() - start
        return Detections(boxes_xyxy_px=merged_boxes, scores=merged_scores), times

    def _run_region(
        self, image_bgr: np.ndarray, region: Region, session: Session, clock: Callable[[], float]
    ) -> _RegionResult:
        """The boxes one region owns above the vote floor, in image pixels; `clock` measures its CPU (the thread's
        own when it runs beside others, the process's when it has every core)."""
        start, start_cpu = time.perf_counter(), clock()
        dets = session.run(["dets"], {self._input_name: region_tensor(image_bgr, region)})[0][0]
        dets = np.asarray(dets, dtype=np.float64).reshape(-1, 5)
        dets = dets[dets[:, 4] >= min(VOTE_FLOOR, self.score_threshold)]
        found = dets[:, :4] / region.scale + (region.x0, region.y0, region.x0, region.y0)
        found[:, [0, 2]] = found[:, [0, 2]].clip(region.x0, region.x1)
        found[:, [1, 3]] = found[:, [1, 3]].clip(region.y0, region.y1)
        mine = region.owns(found) & (found[:, 2] - found[:, 0] > 1.0) & (found[:, 3] - found[:, 1] > 1.0)
        return _RegionResult(found[mine], dets[mine, 4], time.perf_counter() - start, clock() - start_cpu)


@dataclass(frozen=True)
class _RegionResult:
    boxes: np.ndarray
    scores: np.ndarray
    wall_s: float
    cpu_s: float


def schedule(plan: Sequence[Region], workers: int) -> tuple[list[int], list[int]]:
    """Which regions of a plan run alone on every thread and which side by side, one thread each (largest first).

    RTMDet-nano splits poorly across cores (two intra-op threads: ~1.4x on a 640 px pass), whereas whole regions
    side by side scale ~1.7x on two cores: the calibrated Town Centre plan (four regions of 0.05-0.23 MPx) detects
    in 38 instead of 64 ms of wall and 66 instead of 91 ms of CPU. A region larger than an even share of the plan
    would keep one core busy long after the others are done, so it runs alone on all of them (the uncalibrated
    plan's 1280 px pass), as does a region with nothing to run beside it.
    """
    order = sorted(range(len(plan)), key=lambda k: -plan[k].input_pixels)
    total = sum(region.input_pixels for region in plan)
    alone = [k for k in order if plan[k].input_pixels * workers > total]
    side_by_side = [k for k in order if k not in alone]
    if workers == 1 or len(side_by_side) < 2:
        return order, []
    return alone, side_by_side


def decode(dets: np.ndarray, placement: Letterbox, image_hw: tuple[int, ...], score_threshold: float) -> Detections:
    """Threshold, map back to image pixels, clip, drop boxes clipped to nothing, sort by score (stable)."""
    dets = np.asarray(dets, dtype=np.float64).reshape(-1, 5)
    dets = dets[dets[:, 4] >= score_threshold]
    height, width = image_hw[:2]
    boxes = placement.to_image(dets[:, :4])
    boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0.0, width)
    boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0.0, height)
    keep = (boxes[:, 2] - boxes[:, 0] > 1.0) & (boxes[:, 3] - boxes[:, 1] > 1.0)
    boxes, scores = boxes[keep], dets[keep, 4]
    order = np.argsort(-scores, kind="stable")
    return Detections(boxes_xyxy_px=boxes[order], scores=scores[order])
