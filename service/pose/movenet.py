"""MoveNet SinglePose (Thunder 256 px, Lightning 192 px) on person crops: boxes in, COCO-17 keypoints in pixels out.

Crops: a square centred on the detector box with side 1.25 x the box's longer side (MoveNet was trained on people
filling roughly that much of the square), outside-image parts black, resized to the model's input, RGB int32 NHWC
(the graph normalises internally). Corners and side are whole pixels so that the map back,
`image = corner + normalised * side`, is exact and testable.

Batching: the converted graphs declare input [1, H, W, 3], and making the batch dimension symbolic is not enough:
the decoding head hard-codes batch 1 (Reshape to [1, 64, 64, 1], GatherND indices with a leading 0, Reshape to
[17, 17, -1]), so the edited graph fails at its first Reshape. The backbone (all the convolutions, nearly all the
arithmetic) is batch-agnostic, though. So, when the `onnx` package is importable, the graph is split in memory at the
first Reshape: the backbone runs once on all crops with a symbolic batch dimension, and the cheap head runs per
crop on its slice of the backbone's outputs. The split is checked at load time against the untouched graph on a
fixed input (they must agree to float rounding, or the loader falls back to the plain per-crop loop); the shared
files are never modified.

Measured (`posemetry bench pose` and per-crop timings, 2-core Xeon @ 2.5 GHz, onnxruntime 1.31, batched and loop
runs interleaved): batching 15-20 crops is no faster than the loop for either model, at 1 or 2 threads (the
differences were within the run-to-run noise, in both directions; best single-thread cost ~42-44 ms per Thunder
crop and ~12.5 ms per Lightning crop either way). Convolutions on 64x64 feature maps already
keep the CPU's GEMM kernels busy at batch 1, so there is nothing for a batch to amortise but the ~0.1 ms per-run
overhead. The pipeline therefore loops by default (no `onnx` import, no split at load time); `batch=True` stays
for hardware where it may pay (many-core CPUs, GPUs), and the benchmark keeps comparing both.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import cv2
import numpy as np

from .model_files import POSE_INPUT_PX, PoseModelName
from .sessions import make_session
from .types import COCO17_KEYPOINTS

log = logging.getLogger(__name__)

INPUT_PX: Final[dict[str, int]] = POSE_INPUT_PX
CROP_SCALE: Final = 1.25
INPUT_NAME: Final = "input"
OUTPUT_NAME: Final = "output_0"
# The largest batch the backbone is given at once: bounds memory (Thunder: ~20 MB of activations per crop).
MAX_BATCH: Final = 32
# Largest difference allowed between the split and the original graph's outputs (0..1 coordinates and scores).
SPLIT_TOLERANCE: Final = 1e-5


@dataclass(frozen=True)
class CropWindow:
    """A whole-pixel square of the image: columns x0..x0+side, rows y0..y0+side (may extend past the image)."""

    x0: int
    y0: int
    side: int

    def to_image(self, xy_normalised: np.ndarray) -> np.ndarray:
        """(..., 2) x, y in 0..1 over the crop to image pixels."""
        return np.asarray(xy_normalised, dtype=np.float64) * self.side + (self.x0, self.y0)

    def to_normalised(self, xy_image: np.ndarray) -> np.ndarray:
        """(..., 2) image pixels to 0..1 over the crop (inverse of `to_image`)."""
        return (np.asarray(xy_image, dtype=np.float64) - (self.x0, self.y0)) / self.side


def crop_window(box_xyxy: tuple[float, float, float, float] | np.ndarray, scale: float = CROP_SCALE) -> CropWindow:
    """The square centred (to half a pixel) on the box, side `scale` x its longer side."""
    left, top, right, bottom = (float(v) for v in box_xyxy)
    side = max(1, round(scale * max(right - left, bottom - top)))
    return CropWindow(x0=round((left + right - side) / 2), y0=round((top + bottom - side) / 2), side=side)


def extract_crop(image_bgr: np.ndarray, window: CropWindow, out_px: int) -> np.ndarray:
    """(out_px, out_px, 3) uint8 RGB: the window, black where it leaves the image, resized (area filter downwards)."""
    height, width = image_bgr.shape[:2]
    side = window.side
    square = np.zeros((side, side, 3), dtype=np.uint8)
    x_lo, y_lo = max(window.x0, 0), max(window.y0, 0)
    x_hi, y_hi = min(window.x0 + side, width), min(window.y0 + side, height)
    if x_hi > x_lo and y_hi > y_lo:
        square[y_lo - window.y0 : y_hi - window.y0, x_lo - window.x0 : x_hi - window.x0] = image_bgr[
            y_lo:y_hi, x_lo:x_hi
        ]
    interpolation = cv2.INTER_AREA if side > out_px else cv2.INTER_LINEAR
    resized = cv2.resize(square, (out_px, out_px), interpolation=interpolation)
    return cv2.cvtColor(resized, cv2.COLOR_BGR2RGB)


@dataclass(frozen=True)
class PoseOutput:
    """Keypoints of the people in one image, in the order of the boxes given."""

    keypoints_px: np.ndarray
    """(N, 17, 2) x, y in image pixels."""
    scores: np.ndarray
    """(N, 17) confidence in [0, 1]."""


def _split_graph(model_bytes: bytes) -> tuple[bytes, bytes, list[str]] | None:
    """(backbone with a symbolic batch dim, batch-1 head, names of the tensors between them), or None if unsplittable.

    The cut is the first Reshape: in the tf2onnx export every node before it is convolution/activation/transpose
    work that is indifferent to the batch size, and every node from it on is decoding.
    """
    try:
        import onnx
    except ImportError:
        return None
    model = onnx.load_from_string(model_bytes)
    nodes = list(model.graph.node)
    cut = next((i for i, node in enumerate(nodes) if node.op_type == "Reshape"), None)
    if cut is None:
        return None
    produced = {out for node in nodes[:cut] for out in node.output}
    between: list[str] = []
    for node in nodes[cut:]:
        for name in node.input:
            if name in produced and name not in between:
                between.append(name)
    if not between:
        return None

    backbone = onnx.ModelProto()
    backbone.CopyFrom(model)
    del backbone.graph.node[cut:]
    del backbone.graph.output[:]
    del backbone.graph.value_info[:]
    backbone.graph.output.extend(onnx.helper.make_tensor_value_info(n, onnx.TensorProto.FLOAT, None) for n in between)
    backbone.graph.input[0].type.tensor_type.shape.dim[0].dim_param = "batch"
    used = {name for node in backbone.graph.node for name in node.input}
    kept = [init for init in backbone.graph.initializer if init.name in used]
    del backbone.graph.initializer[:]
    backbone.graph.initializer.extend(kept)

    head = onnx.ModelProto()
    head.CopyFrom(model)
    del head.graph.node[:cut]
    del head.graph.input[:]
    del head.graph.value_info[:]
    head.graph.input.extend(onnx.helper.make_tensor_value_info(n, onnx.TensorProto.FLOAT, None) for n in between)
    used = {name for node in head.graph.node for name in node.input}
    kept = [init for init in head.graph.initializer if init.name in used]
    del head.graph.initializer[:]
    head.graph.initializer.extend(kept)
    return backbone.SerializeToString(), head.SerializeToString(), between


class MoveNet:
    """One MoveNet SinglePose model; crops batched through a split graph when possible, else one run per crop."""

    def __init__(
        self, model_path: Path, pose_model: PoseModelName, *, threads: int | None = None, batch: bool = False
    ) -> None:
        self.pose_model = pose_model
        self.input_px = INPUT_PX[pose_model]
        model_bytes = Path(model_path).read_bytes()
        self.full = make_session(model_bytes, threads)
        self.backbone = self.head = None
        self._between: list[str] = []
        if batch:
            split = _split_graph(model_bytes)
            if split is None:
                log.info("%s: graph not splittable here (no `onnx` package?); crops run one at a time", pose_model)
            else:
                backbone_bytes, head_bytes, self._between = split
                self.backbone = make_session(backbone_bytes, threads)
                self.head = make_session(head_bytes, threads)
                if not self._split_agrees():
                    log.warning("%s: split graph disagrees with the original; crops run one at a time", pose_model)
                    self.backbone = self.head = None

    @property
    def batched(self) -> bool:
        """Whether crops go through the backbone together (False: the plain per-crop loop)."""
        return self.backbone is not None

    def _split_agrees(self) -> bool:
        """The split graph, run as a batch, reproduces the untouched one (to float rounding) on two fixed crops."""
        rng = np.random.default_rng(0)
        crops = rng.integers(0, 256, (2, self.input_px, self.input_px, 3)).astype(np.int32)
        reference = np.concatenate([self.full.run([OUTPUT_NAME], {INPUT_NAME: c[None]})[0] for c in crops])
        try:
            split = self._run_split(crops)
        except Exception:  # an onnxruntime failure of the edited graph means: do not use it
            log.exception("%s: split graph failed to run", self.pose_model)
            return False
        # Different graph optimisations (fusions) of the two graphs round differently: ~2e-7 of the crop side.
        return bool(np.allclose(reference, split, rtol=0.0, atol=SPLIT_TOLERANCE))

    def _run_split(self, crops: np.ndarray) -> np.ndarray:
        assert self.backbone is not None and self.head is not None
        outputs = []
        for start in range(0, len(crops), MAX_BATCH):
            features = self.backbone.run(self._between, {INPUT_NAME: crops[start : start + MAX_BATCH]})
            for i in range(len(features[0])):
                feed = {name: f[i : i + 1] for name, f in zip(self._between, features, strict=True)}
                outputs.append(self.head.run([OUTPUT_NAME], feed)[0])
        return np.concatenate(outputs)

    def infer(self, crops: np.ndarray) -> np.ndarray:
        """(N, 17, 3) y, x, score (0..1 over each crop) for (N, S, S, 3) int32 RGB crops."""
        if len(crops) == 0:
            return np.zeros((0, COCO17_KEYPOINTS, 3), dtype=np.float32)
        if self.batched:
            raw = self._run_split(crops)
        else:
            raw = np.concatenate([self.full.run([OUTPUT_NAME], {INPUT_NAME: c[None]})[0] for c in crops])
        return raw.reshape(len(crops), COCO17_KEYPOINTS, 3)

    def __call__(self, image_bgr: np.ndarray, boxes_xyxy_px: np.ndarray) -> PoseOutput:
        """Keypoints in image pixels for each box of one image."""
        windows = [crop_window(box) for box in boxes_xyxy_px]
        if not windows:
            return PoseOutput(np.zeros((0, COCO17_KEYPOINTS, 2)), np.zeros((0, COCO17_KEYPOINTS)))
        crops = np.stack([extract_crop(image_bgr, w, self.input_px) for w in windows]).astype(np.int32)
        raw = self.infer(crops)
        keypoints = np.stack([w.to_image(r[:, 1::-1]) for w, r in zip(windows, raw, strict=True)])
        return PoseOutput(keypoints_px=keypoints, scores=raw[:, :, 2].astype(np.float64))
