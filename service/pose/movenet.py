"""MoveNet SinglePose (Thunder 256 px, Lightning 192 px) on person crops: boxes in, COCO-17 keypoints in pixels out.

Crops: a square centred on the detector box with side 1.25 x the box's longer side (MoveNet was trained on people
filling roughly that much of the square), outside-image parts black, resized to the model's input, RGB.
Corners and side are whole pixels so that the map back, `image = corner + normalised * side`, is exact and testable.

Preamble: the converted graphs take int32 NHWC RGB and start with six elementwise nodes (cast, unstack, x * 1/127.5
- 1, transpose to NCHW) that cost onnxruntime as much as a dozen convolutions. When the `onnx` package is present,
the graph is rebuilt in memory without them and OpenCV does the same float32 arithmetic in one pass; the
rebuilt graph is checked at load time against the untouched file on fixed crops (bit-identical in practice, or
the untouched graph is used). The shared files are never modified.

Crop modes (measured with `posemetry bench pose` and per-crop CPU times, 2-core Xeon with AVX-512, onnxruntime
1.32; Thunder ~19 ms and Lightning ~5 ms of one core per crop):
- `concurrent` (default): crops are handed to a pool of one thread per core, each running a session call on one
  core (intra-op threads 1). A 1.2 GMAC MobileNetV2 on 64x64 maps splits poorly across cores (2 intra-op threads
  gave 1.35x on one crop), whereas whole crops in parallel scale ~1.8-1.9x on two cores.
- `loop`: one crop after another, each on all intra-op threads; the baseline the benchmark compares against.
- `batched`: the batch dimension cannot just be made symbolic, because the decoding head hard-codes batch 1
  (Reshape to [1, 64, 64, 1], GatherND indices with a leading 0, Reshape to [17, 17, -1]). So the graph is split
  at its first Reshape: the batch-agnostic backbone (nearly all the arithmetic) runs on all crops at once with a
  symbolic batch dimension, the cheap head per crop. It is checked at load time like the trimmed graph. Measured
  no faster than the loop on CPU (the 64x64 convolutions already keep the GEMM kernels busy at batch 1, so a
  batch amortises only the ~0.1 ms per-run overhead); kept for hardware where it may pay.

Runtime: onnxruntime float32, or OpenVINO bfloat16 on CPUs that compute in it natively (sessions.py: ~2x less CPU
per crop, keypoints within the float model's response to a one-pixel crop shift); the crop modes work alike on both.

Not done, measured: INT8. onnxruntime's static QDQ quantisation (per-channel s8 weights, u8 activations, MinMax
calibration on 100-200 Town Centre crops from frames outside the test set, decoding head kept in float) runs a
Thunder crop in ~14-15 ms instead of ~24 ms (untrimmed graphs), but moves confident keypoints (score > 0.3) by
3.0 px mean / 7.0 px p95 at the 256-px input and flips 11 % of keypoints across the 0.3 score threshold on
Town Centre crops (5.3 / 14 px on the atrium camera), while shifting the crop by one image pixel moves the float
model's by 2.5 / 5.6 px and flips 7 %. Keeping the FPN in float narrows it (2.7 / 6.0 px, 9 %) at ~18 ms a crop,
no gain left. Not equivalent to the float model, so not used. Re-measured for Lightning with four recipes
(docs/benchmarks/pose.md, speed round): 3.6-3.8 ms a crop instead of 7.2-7.5, keypoints 4.1-4.4 px mean / 13-14 px
p95 off the float model's; a one-pixel crop shift moves them 2.3 / 4.8 px.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

import cv2
import numpy as np

from .model_files import POSE_INPUT_PX, PoseModelName
from .occlusion import fill_boxes
from .sessions import Runtime, Session, default_threads, make_session, thread_pool
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
CropMode = Literal["concurrent", "batched", "loop"]
CROP_MODES: Final[tuple[CropMode, ...]] = ("concurrent", "batched", "loop")


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


def extract_crop(
    image_bgr: np.ndarray, window: CropWindow, out_px: int, masked_xyxy_px: np.ndarray | None = None
) -> np.ndarray:
    """(out_px, out_px, 3) uint8 RGB: the window, black where it leaves the image, resized (area filter downwards).

    `masked_xyxy_px`: boxes (image pixels) filled with black in the crop before resizing: the nearer people in
    front of a hidden person (occlusion.py), so that MoveNet reads the hidden one.
    """
    height, width = image_bgr.shape[:2]
    side = window.side
    x_lo, y_lo = max(window.x0, 0), max(window.y0, 0)
    x_hi, y_hi = min(window.x0 + side, width), min(window.y0 + side, height)
    if (x_hi - x_lo, y_hi - y_lo) == (side, side):
        square = image_bgr[y_lo:y_hi, x_lo:x_hi]  # inside the image: resized straight from a view, no copy
        if masked_xyxy_px is not None:
            square = square.copy()
    else:
        square = np.zeros((side, side, 3), dtype=np.uint8)
        if x_hi > x_lo and y_hi > y_lo:
            square[y_lo - window.y0 : y_hi - window.y0, x_lo - window.x0 : x_hi - window.x0] = image_bgr[
                y_lo:y_hi, x_lo:x_hi
            ]
    if masked_xyxy_px is not None:
        fill_boxes(square, window.x0, window.y0, masked_xyxy_px)
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


@dataclass(frozen=True)
class InputNormalisation:
    """What the converted graph's preamble does to the int32 RGB NHWC crop: `(x - offset) * scale - shift`, NCHW."""

    offset: np.ndarray
    scale: np.ndarray
    shift: np.ndarray

    def __call__(self, crops_rgb: np.ndarray) -> np.ndarray:
        """(N, S, S, 3) uint8 RGB to the (N, 3, S, S) float32 tensor the first convolution reads, bit for bit.

        OpenCV's blob builder does the subtract-multiply and the layout change in one pass (~0.2 ms per Thunder
        crop, a quarter of the equivalent numpy expression); it takes one scale for all channels, which MoveNet has.
        """
        if np.ptp(self.scale) == 0 and np.ptp(self.shift) == 0:
            blob = cv2.dnn.blobFromImages(list(crops_rgb), float(self.scale[0]), mean=tuple(map(float, self.offset)))
            blob -= self.shift[0]
            return blob
        normalised = (crops_rgb.astype(np.float32) - self.offset) * self.scale - self.shift
        return np.ascontiguousarray(normalised.transpose(0, 3, 1, 2))


PREAMBLE_OPS: Final = ("Cast", "Split", "Sub", "Mul", "Sub", "Transpose")


def _trim_preamble(model_bytes: bytes) -> tuple[bytes, InputNormalisation] | None:
    """The graph starting at its first convolution (input: normalised float NCHW), and the normalisation it skips.

    tf2onnx keeps TF.js's preamble (cast int32 to float, unstack the batch, subtract 0, multiply by 1/127.5,
    subtract 1, NHWC to NCHW) as six elementwise nodes over the whole crop; onnxruntime runs them at ~1.5 ms per
    Thunder crop (~1 ms per Lightning crop, 15 % of its time), as much as a dozen convolutions. The same float32
    arithmetic in `InputNormalisation` costs ~0.2 ms. None when the graph does
    not start with exactly that preamble (another conversion): then the untouched graph is used.
    """
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError:
        return None
    model = onnx.load_from_string(model_bytes)
    nodes = list(model.graph.node)
    ops = tuple(node.op_type for node in nodes[: len(PREAMBLE_OPS) + 1])
    if ops != (*PREAMBLE_OPS, "Conv"):
        return None
    cast, split, sub, mul, sub_1, transpose = nodes[: len(PREAMBLE_OPS)]
    chained = [cast.input[0] == INPUT_NAME, split.input[0] == cast.output[0], sub.input[0] == split.output[0]]
    chained += [mul.input[0] == sub.output[0], sub_1.input[0] == mul.output[0], transpose.input[0] == sub_1.output[0]]
    perm = next((list(a.ints) for a in transpose.attribute if a.name == "perm"), None)
    inits = {init.name: init for init in model.graph.initializer}
    constants = [inits.get(node.input[1]) for node in (sub, mul, sub_1)]
    if not all(chained) or perm != [0, 3, 1, 2] or any(c is None for c in constants):
        return None
    offset, scale, shift = (numpy_helper.to_array(c).astype(np.float32).reshape(-1) for c in constants)  # type: ignore[arg-type]
    conv_input = transpose.output[0]
    if sum(conv_input in n.input for n in nodes) != 1:
        return None
    size = [d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]  # [1, S, S, 3]
    del model.graph.node[: len(PREAMBLE_OPS)]
    for name_list in (n.input for n in model.graph.node):
        for k, name in enumerate(name_list):
            if name == conv_input:
                name_list[k] = INPUT_NAME
    del model.graph.input[:]
    model.graph.input.append(
        onnx.helper.make_tensor_value_info(INPUT_NAME, onnx.TensorProto.FLOAT, [size[0], 3, size[1], size[2]])
    )
    used = {name for node in model.graph.node for name in node.input}
    kept = [init for init in model.graph.initializer if init.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(kept)
    del model.graph.value_info[:]
    return model.SerializeToString(), InputNormalisation(offset, scale, shift)


class MoveNet:
    """One MoveNet SinglePose model on a frame's person crops, in one of three `CropMode`s (see the module notes)."""

    def __init__(
        self,
        model_path: Path,
        pose_model: PoseModelName,
        *,
        threads: int | None = None,
        crops: CropMode = "concurrent",
        runtime: Runtime = "onnxruntime",
    ) -> None:
        if crops not in CROP_MODES:
            raise ValueError(f"unknown crop mode {crops!r}; expected one of {', '.join(CROP_MODES)}")
        self.pose_model = pose_model
        self.input_px = INPUT_PX[pose_model]
        self.workers = threads or default_threads()
        self.crop_mode: CropMode = crops
        self.runtime: Runtime = runtime
        model_bytes = Path(model_path).read_bytes()
        # Concurrent crops each run on one core; the loop and the batch use the session's intra-op threads.
        session_threads = 1 if crops == "concurrent" else self.workers
        streams = self.workers if crops == "concurrent" else 1
        self.normalise: InputNormalisation | None = None
        graph_bytes = model_bytes
        trimmed = _trim_preamble(model_bytes)
        if trimmed is not None:
            # The check compares graphs, so both run in float32 on onnxruntime, whatever runs them later: compiling
            # both for OpenVINO as well cost ~0.3 s each at every start.
            self.full = make_session(trimmed[0], 1)
            self.normalise = trimmed[1]
            if self._trim_agrees(make_session(model_bytes, 1)):
                graph_bytes = trimmed[0]
            else:
                log.warning("%s: trimmed graph disagrees with the original; using the original", pose_model)
                self.normalise = None
        if self.normalise is None or runtime != "onnxruntime" or session_threads != 1:
            self.full = make_session(graph_bytes, session_threads, runtime=runtime, streams=streams)
        self.backbone = self.head = None
        self._between: list[str] = []
        if crops == "batched" and runtime != "onnxruntime":
            log.info("%s: the split graph is checked in onnxruntime only; crops run one at a time", pose_model)
        elif crops == "batched":
            split = _split_graph(graph_bytes)
            if split is None:
                log.info("%s: graph not splittable here (no `onnx` package?); crops run one at a time", pose_model)
            else:
                backbone_bytes, head_bytes, self._between = split
                self.backbone = make_session(backbone_bytes, self.workers)
                self.head = make_session(head_bytes, self.workers)
                if not self._split_agrees():
                    log.warning("%s: split graph disagrees with the original; crops run one at a time", pose_model)
                    self.backbone = self.head = None

    @property
    def batched(self) -> bool:
        """Whether crops go through the backbone together (False: one run per crop)."""
        return self.backbone is not None

    @property
    def trimmed(self) -> bool:
        """Whether the input preamble runs outside the graph (False: the untouched converted graph)."""
        return self.normalise is not None

    def prepare(self, crops_rgb: np.ndarray) -> np.ndarray:
        """(N, S, S, 3) uint8 RGB crops as the session's input tensor."""
        if self.normalise is None:
            return crops_rgb.astype(np.int32)
        return self.normalise(crops_rgb)

    def _fixed_crops(self) -> np.ndarray:
        rng = np.random.default_rng(0)
        return rng.integers(0, 256, (2, self.input_px, self.input_px, 3)).astype(np.uint8)

    def _trim_agrees(self, original: Session) -> bool:
        """The trimmed graph after `InputNormalisation` reproduces the untouched graph on two fixed crops."""
        crops = self._fixed_crops()
        feeds = ({INPUT_NAME: crop[None].astype(np.int32)} for crop in crops)
        reference = np.concatenate([original.run([OUTPUT_NAME], feed)[0] for feed in feeds])
        try:
            trimmed = self._run_each(self.prepare(crops))
        except Exception:  # an onnxruntime failure of the edited graph means: do not use it
            log.exception("%s: trimmed graph failed to run", self.pose_model)
            return False
        return bool(np.allclose(reference, trimmed, rtol=0.0, atol=SPLIT_TOLERANCE))

    def _split_agrees(self) -> bool:
        """The split graph, run as a batch, reproduces the whole graph (to float rounding) on two fixed crops."""
        tensors = self.prepare(self._fixed_crops())
        reference = self._run_each(tensors)
        try:
            split = self._run_split(tensors)
        except Exception:  # an onnxruntime failure of the edited graph means: do not use it
            log.exception("%s: split graph failed to run", self.pose_model)
            return False
        # Different graph optimisations (fusions) of the two graphs round differently: ~2e-7 of the crop side.
        return bool(np.allclose(reference, split, rtol=0.0, atol=SPLIT_TOLERANCE))

    def _run_one(self, tensor: np.ndarray) -> np.ndarray:
        return self.full.run([OUTPUT_NAME], {INPUT_NAME: tensor[None]})[0]

    def _run_each(self, tensors: np.ndarray) -> np.ndarray:
        return np.concatenate([self._run_one(t) for t in tensors])

    def _run_split(self, tensors: np.ndarray) -> np.ndarray:
        assert self.backbone is not None and self.head is not None
        outputs = []
        for start in range(0, len(tensors), MAX_BATCH):
            features = self.backbone.run(self._between, {INPUT_NAME: tensors[start : start + MAX_BATCH]})
            for i in range(len(features[0])):
                feed = {name: f[i : i + 1] for name, f in zip(self._between, features, strict=True)}
                outputs.append(self.head.run([OUTPUT_NAME], feed)[0])
        return np.concatenate(outputs)

    def crop_and_run(self, image_bgr: np.ndarray, window: CropWindow) -> np.ndarray:
        """(1, 17, 3) raw output for one window of the image (the unit of work of the concurrent pool)."""
        return self._run_one(self.prepare(extract_crop(image_bgr, window, self.input_px)[None])[0])

    def _run_concurrently(self, tensors: np.ndarray) -> np.ndarray:
        """One crop per thread at a time, each on one core; onnxruntime releases the GIL while it runs."""
        if self.workers == 1 or len(tensors) == 1:
            return self._run_each(tensors)
        return np.concatenate(list(thread_pool(self.workers).map(self._run_one, tensors)))

    def infer(self, crops_rgb: np.ndarray) -> np.ndarray:
        """(N, 17, 3) y, x, score (0..1 over each crop) for (N, S, S, 3) uint8 RGB crops."""
        if len(crops_rgb) == 0:
            return np.zeros((0, COCO17_KEYPOINTS, 3), dtype=np.float32)
        tensors = self.prepare(np.asarray(crops_rgb, dtype=np.uint8))
        if self.batched:
            raw = self._run_split(tensors)
        elif self.crop_mode == "concurrent":
            raw = self._run_concurrently(tensors)
        else:
            raw = self._run_each(tensors)
        return raw.reshape(len(crops_rgb), COCO17_KEYPOINTS, 3)

    def __call__(self, image_bgr: np.ndarray, boxes_xyxy_px: np.ndarray) -> PoseOutput:
        """Keypoints in image pixels for each box of one image."""
        return read_people(image_bgr, boxes_xyxy_px, [self] * len(boxes_xyxy_px))


def read_people(image_bgr: np.ndarray, boxes_xyxy_px: np.ndarray, readers: Sequence[MoveNet]) -> PoseOutput:
    """Keypoints in image pixels for each box of one image, box k read by `readers[k]` (Thunder or Lightning).

    Concurrent readers share one pool for all of a frame's crops, whatever their model, the costliest model's crops
    first (longest processing time first): reading one model's people after the other's left a core idle while the
    last Thunder crop ran (~19 ms of wall on a frame with one near person). Crops are independent and each runs on
    the same one-thread session either way, so the keypoints are those of one call per model, bit for bit.
    """
    windows = [crop_window(box) for box in boxes_xyxy_px]
    if len(readers) != len(windows):
        raise ValueError(f"{len(windows)} boxes but {len(readers)} readers")
    if not windows:
        return PoseOutput(np.zeros((0, COCO17_KEYPOINTS, 2)), np.zeros((0, COCO17_KEYPOINTS)))
    raw = np.empty((len(windows), COCO17_KEYPOINTS, 3), dtype=np.float32)
    workers = min(reader.workers for reader in readers)
    if all(reader.crop_mode == "concurrent" for reader in readers) and workers > 1 and len(windows) > 1:
        # Cropping and normalising in the pool too: no serial preprocessing before the first crop runs.
        order = sorted(range(len(windows)), key=lambda k: -readers[k].input_px)
        results = thread_pool(workers).map(lambda k: readers[k].crop_and_run(image_bgr, windows[k]), order)
        for k, result in zip(order, results, strict=True):
            raw[k] = result.reshape(COCO17_KEYPOINTS, 3)
    else:
        for reader in {id(r): r for r in readers}.values():
            mine = [k for k, r in enumerate(readers) if r is reader]
            raw[mine] = reader.infer(np.stack([extract_crop(image_bgr, windows[k], reader.input_px) for k in mine]))
    keypoints = np.stack([w.to_image(r[:, 1::-1]) for w, r in zip(windows, raw, strict=True)])
    return PoseOutput(keypoints_px=keypoints, scores=raw[:, :, 2].astype(np.float64))
