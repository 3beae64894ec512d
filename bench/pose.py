"""Pose-pipeline speed on real surveillance frames: detector vs pose time, Thunder vs Lightning, concurrent vs loop.

Targets (per 1080p frame of ~15 people, CPU): <= 150 ms with Thunder, <= 80 ms with Lightning. Frames are the
Oxford Town Centre clip frames (`clip_*.jpg`), decoded once up front so JPEG decoding is not timed. The
concurrent estimator (the service's default: one crop per core at a time) and the plain per-crop loop (each crop
on all cores in turn, the baseline) of one model are run alternately on each frame, so load from other
processes on a shared machine hits both alike and their difference is a paired comparison. CPU time per frame
(all threads) is reported beside wall time: on a shared machine it is the steadier measure of the work done.
Because the number of people varies per frame, the report also gives the cost scaled to a 15-person frame
(detector time plus 15 x the measured per-person pose time), which is what the targets are stated for.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np

from service.pose.model_files import PoseModelName

Progress = Callable[[str], None]
TARGET_MS: Final[dict[str, float]] = {"thunder": 150.0, "lightning": 80.0}
TARGET_PEOPLE: Final = 15
MODES: Final = ("concurrent", "loop")


@dataclass
class PoseTiming:
    """Per-frame measurements of one estimator (one model, one crop mode)."""

    pose_model: str
    mode: str
    total_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    detector_s: list[float] = field(default_factory=list)
    pose_s: list[float] = field(default_factory=list)
    people: list[int] = field(default_factory=list)

    def ms(self, values: Sequence[float], q: float | None = None) -> float:
        if not values:
            return float("nan")
        data = 1000.0 * np.asarray(values)
        return float(data.mean() if q is None else np.percentile(data, q))

    @property
    def frames_per_s(self) -> float:
        return len(self.total_s) / sum(self.total_s) if self.total_s else float("nan")

    @property
    def pose_ms_per_person(self) -> float:
        people = sum(self.people)
        return 1000.0 * sum(self.pose_s) / people if people else float("nan")

    @property
    def ms_at_target_people(self) -> float:
        """Mean detector time plus TARGET_PEOPLE x the mean per-person pose time (crop + inference + decode)."""
        return self.ms(self.detector_s) + TARGET_PEOPLE * self.pose_ms_per_person


@dataclass
class PoseBenchmark:
    timings: list[PoseTiming]
    frames: int
    repeats: int
    threads: int
    detector_input_px: int


def _load_frames(frames_dir: Path) -> list[np.ndarray]:
    import cv2

    paths = sorted(Path(frames_dir).glob("clip_*.jpg"))
    if not paths:
        raise FileNotFoundError(f"no clip_*.jpg frames in {frames_dir}")
    frames = [cv2.imread(str(p)) for p in paths]
    missing = [str(p) for p, f in zip(paths, frames, strict=True) if f is None]
    if missing:
        raise OSError(f"cannot read {', '.join(missing)}")
    return frames  # type: ignore[return-value]


def run_pose_benchmark(
    model_dir: Path,
    frames_dir: Path,
    pose_models: Sequence[PoseModelName] = ("thunder", "lightning"),
    repeats: int = 2,
    progress: Progress = lambda _message: None,
    *,
    threads: int | None = None,
    detector_input_px: int = 640,
) -> PoseBenchmark:
    """Time the pipeline on every clip frame, `repeats` passes, for each model in both crop modes."""
    from service.pose.pipeline import TopDownPose
    from service.pose.sessions import default_threads

    frames = _load_frames(frames_dir)
    timings: list[PoseTiming] = []
    for pose_model in pose_models:
        progress(f"{pose_model}: loading sessions")
        estimators = {
            mode: TopDownPose(model_dir, pose_model, detector_input_px=detector_input_px, threads=threads, crops=mode)
            for mode in MODES
        }
        results = {mode: PoseTiming(pose_model, mode) for mode in MODES}
        for estimator in estimators.values():  # warm-up: first runs allocate arenas and pick kernels
            estimator(frames[0])
        for repeat in range(repeats):
            progress(f"{pose_model}: pass {repeat + 1}/{repeats} over {len(frames)} frames")
            for frame in frames:
                for mode, estimator in estimators.items():
                    start, start_cpu = time.perf_counter(), time.process_time()
                    estimator(frame)
                    elapsed, elapsed_cpu = time.perf_counter() - start, time.process_time() - start_cpu
                    result, stages = results[mode], estimator.last_times
                    result.total_s.append(elapsed)
                    result.cpu_s.append(elapsed_cpu)
                    result.detector_s.append(stages.detector_s)
                    result.pose_s.append(stages.pose_s)
                    result.people.append(stages.people)
        timings.extend(results.values())
    return PoseBenchmark(
        timings=timings,
        frames=len(frames),
        repeats=repeats,
        threads=threads or default_threads(),
        detector_input_px=detector_input_px,
    )


def pose_lines(result: PoseBenchmark) -> list[str]:
    """The report as printable lines (terminal and docs alike)."""
    lines = [
        f"pose pipeline: RTMDet-nano @ {result.detector_input_px} + MoveNet per person, onnxruntime CPU, "
        f"{result.threads} intra-op threads; {result.frames} Town Centre 1080p frames x {result.repeats} passes",
        f"  {'model':<10} {'crops':<10} {'mean':>7} {'min':>7} {'p50':>7} {'p90':>7} {'cpu':>7} {'fps':>6} "
        f"{'detector':>9} {'pose':>7} {'people':>6} {'ms/person':>9} {f'@{TARGET_PEOPLE} people':>13}  target",
    ]
    for t in result.timings:
        target = TARGET_MS.get(t.pose_model, float("nan"))
        at_target = t.ms_at_target_people
        verdict = "meets" if at_target <= target else "MISSES"
        lines.append(
            f"  {t.pose_model:<10} {t.mode:<10} {t.ms(t.total_s):7.1f} {t.ms(t.total_s, 0):7.1f} "
            f"{t.ms(t.total_s, 50):7.1f} {t.ms(t.total_s, 90):7.1f} {t.ms(t.cpu_s):7.1f} {t.frames_per_s:6.2f} "
            f"{t.ms(t.detector_s):9.1f} "
            f"{t.ms(t.pose_s):7.1f} "
            f"{np.mean(t.people):6.1f} {t.pose_ms_per_person:9.2f} {at_target:13.1f}  {verdict} <= {target:g} ms"
        )
    lines += [
        "  (ms per frame; cpu: mean CPU ms per frame, all threads; detector/pose: mean ms per frame of each stage,",
        "  pose includes cropping; on a shared machine `min` and `cpu` are the best estimates of the uncontended cost)",
        "  concurrent: each crop runs on one core, as many crops at once as threads (small convnets scale poorly",
        "  across cores, so whole crops in parallel beat splitting each crop's layers); loop: one crop at a time on",
        "  all threads. Both feed MoveNet a normalised NCHW tensor (the converted graph's int32 preamble trimmed in",
        "  memory, checked against the untouched graph at load time); the detector sees a stride-padded letterbox",
        "  (640 x 384 for 16:9), not a 640 x 640 square.",
    ]
    return lines
