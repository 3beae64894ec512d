"""One `posemetry analyze` run: pose on every frame, one calibration from all of them, then every frame measured.

The order matters. A single frame holds a dozen people at most, too few to pin a focal length; pooled over a
video they are hundreds, so the camera is solved once from the evidence of all frames (repeats of people standing
still collapsed, see service.geometry.evidence) and that one calibration then measures every frame, exactly as
the service's workers measure stored frames with a camera's current calibration. The steps are the service's
own: `TopDownPose` finds people, `people_from_detections` decides who is evidence and why not,
`solve_evidence` calibrates, `measure_people` places people and measures pairs.

Guided pass (default): the first pose pass knows nothing of the camera and searches every frame with the fixed
uncalibrated policy. Once that pass has calibrated the camera from enough people (`--min-people`), pose runs again
on every frame with the calibration guiding the detector (service/pose/regions.py: each band of the frame at the
scale that makes its people the detector's favourite size, only where the first pass saw people's feet), and the
camera is solved again from that pass's evidence: the service's steady state, where a calibrated camera's frames
are searched the calibrated way. It doubles the pose time; `--no-guided` skips it. A first camera solved from
fewer people is not used to guide (on the atrium frames a 13-person camera put the horizon through the floor and
the guided pass found 244 people where the first had found 312).

Only the people (centres, verdicts, compact keypoints) of every frame are held between the passes; a frame's pairs
and pictures are written as it is measured and then dropped, so a long video costs time, not memory.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from service.domain import PersonIn
from service.frames.keypoints import as_static, people_from_detections
from service.frames.measure import measure_people
from service.geometry import Calibration, SolveOptions
from service.geometry.evidence import EvidenceSolve, solve_evidence
from service.pose.types import PoseEstimator

from .analysis import Analysis, AnalyzedFrame, Evidence, Observer
from .errors import AnalyzeError
from .options import AnalyzeOptions
from .pictures import PictureWriter
from .records import CalibrationRole
from .sources import FrameSource, SkippedFrame, SourceFrame, open_source
from .writers import TableWriter, frame_record, prepare_output, write_calibration


def detect(
    source: FrameSource,
    estimator: PoseEstimator,
    observer: Observer,
    calibration: Calibration | None = None,
    feet_box_px: tuple[float, float, float, float] | None = None,
) -> tuple[list[AnalyzedFrame], list]:
    """Pose on every frame the source delivers; each person reduced to centres and an evidence verdict.

    With a calibration (the guided pass), the estimator searches where and at the scale people can appear.
    """
    frames: list[AnalyzedFrame] = []
    skipped: list[SkippedFrame] = []
    observer.begin("pose" if calibration is None else "guided", source.planned())
    for item in source.frames():
        if isinstance(item, SkippedFrame):
            skipped.append(item)
            observer.note(f"skipped {_frame_name(item.index, item.file)}: {item.reason}")
            observer.advance()
            continue
        if calibration is None:
            found = estimator(item.image)
        else:
            found = _guided(estimator, item.image, calibration, feet_box_px)
        people = [_compact(p) for p in people_from_detections(found, source.image_size_px)]
        frames.append(AnalyzedFrame(item.index, item.time_s, item.file, people))
        observer.advance(people=len(people))
    return frames, skipped


def mark_static(frames: Sequence[AnalyzedFrame], static_after_s: float) -> list[AnalyzedFrame]:
    """The frames with people at static spots (service.cameras.static_spots: a mannequin, a poster) marked
    unusable, as the service marks them: no evidence, no violation. Needs frame times; without them (a folder
    of images) the frames are returned as they are."""
    from service.cameras.static_rule import static_in_recording

    if any(frame.time_s is None for frame in frames):
        return list(frames)
    static = static_in_recording(
        [float(frame.time_s or 0.0) for frame in frames],
        [[person.box_px for person in frame.people] for frame in frames],
        static_after_s,
    )
    return [
        replace(
            frame,
            people=[as_static(person) if still else person for person, still in zip(frame.people, marks, strict=True)],
        )
        for frame, marks in zip(frames, static, strict=True)
    ]


def _guided(
    estimator: PoseEstimator,
    image: np.ndarray,
    calibration: Calibration,
    feet_box_px: tuple[float, float, float, float] | None,
) -> list:
    """The estimator guided by a calibration (and where people's feet were seen, when it takes that)."""
    from service.pose.pipeline import TopDownPose

    if isinstance(estimator, TopDownPose):
        return estimator(image, calibration, feet_box_px=feet_box_px)
    return estimator(image, calibration)


# Feet seen in the first pass, as the guided pass's search area: the central 96 % of them (a few false detections
# on a wall must not widen it), grown by this fraction of the frame on every side (people walk a little further).
FEET_QUANTILES = (0.02, 0.98)
FEET_MARGIN = 0.05


def feet_box(
    frames: Sequence[AnalyzedFrame], image_size_px: tuple[int, int]
) -> tuple[float, float, float, float] | None:
    """Where people's feet (box bottom centres) were seen in these frames, grown by FEET_MARGIN; None if nowhere."""
    feet = np.array(
        [((p.box_px[0] + p.box_px[2]) / 2, p.box_px[3]) for f in frames for p in f.people if p.box_px is not None]
    ).reshape(-1, 2)
    if len(feet) < 2:
        return None
    low, high = np.quantile(feet, FEET_QUANTILES, axis=0)
    width, height = image_size_px
    margin_x, margin_y = FEET_MARGIN * width, FEET_MARGIN * height
    # Feet at the bottom edge are people cut by the frame: the box then reaches below it.
    bottom = high[1] + margin_y if high[1] < height - 1 else 1.5 * height
    return (max(0.0, low[0] - margin_x), max(0.0, low[1] - margin_y), min(float(width), high[0] + margin_x), bottom)


def _compact(person: PersonIn) -> PersonIn:
    """Keypoints as one small float32 array instead of 17 lists of Python floats (~6x less memory per person)."""
    if person.keypoints is None:
        return person
    return replace(person, keypoints=np.asarray(person.keypoints, dtype=np.float32))


def _frame_name(index: int, file: str | None) -> str:
    return file if file is not None else f"frame {index}"


def roles_of(evidence: Evidence, solve: EvidenceSolve) -> dict[tuple[int, int], CalibrationRole]:
    """Each usable person's part in the solve: inlier, outlier (solved on, rejected) or unused."""
    used = np.zeros(len(evidence), dtype=bool)
    used[solve.used] = True
    inlier = solve.inlier_mask(len(evidence))
    return {
        owner: "inlier" if inlier[row] else "outlier" if used[row] else "unused"
        for row, owner in enumerate(evidence.owners)
    }


def calibrate_frames(
    frames: Sequence[AnalyzedFrame], image_size_px: tuple[int, int], options: AnalyzeOptions, *, min_people: int = 0
) -> tuple[Evidence, EvidenceSolve]:
    """One solve on the usable people of every frame; none (with the reason) with fewer than `min_people`."""
    evidence = Evidence.of(frames)
    if len(evidence) < min_people:
        error = (
            f"only {len(evidence)} usable people, at least {min_people} needed to pin a focal length (fewer give a "
            "camera that looks solved and is not); analyse more frames (a smaller --stride, more images), give "
            "--focal-px, or lower --min-people"
        )
        return evidence, EvidenceSolve(used=np.zeros(0, dtype=int), calibration=None, error=error)
    # Frame times link one person's observations into one individual (service.geometry.tracks).
    times = [frames[position].time_s for position, _ in evidence.owners]
    solve = solve_evidence(
        evidence.tops_px,
        evidence.bottoms_px,
        options.problem(image_size_px),
        SolveOptions(distortion=options.distortion),
        cap=options.sample_cap,
        times_s=None if any(t is None for t in times) else np.array(times, dtype=float),
        appearance=evidence.appearance,
    )
    return evidence, solve


def _aligned_images(source: FrameSource, frames: Sequence[AnalyzedFrame]) -> Iterator[np.ndarray | None]:
    """The image of each analysed frame, decoded again, in order (None if it no longer decodes)."""
    items = (item for item in source.frames() if isinstance(item, SourceFrame))
    item = next(items, None)
    for frame in frames:
        while item is not None and item.index < frame.index:
            item = next(items, None)
        yield item.image if item is not None and item.index == frame.index else None


def report_frames(analysis: Analysis, out_dir: Path, observer: Observer) -> None:
    """Measure every frame with the one calibration and write it (tables, pictures) as it is measured.

    Streaming: a frame's pairs and pictures are dropped once written, so memory does not grow with the video.
    """
    calibration = analysis.calibration
    threshold_m = analysis.options.threshold_m
    draw = calibration is not None and (analysis.options.write_images or analysis.wants_video)
    images: Iterator[np.ndarray | None] = (
        _aligned_images(analysis.source, analysis.frames) if draw else iter(lambda: None, 0)
    )
    observer.begin("results", len(analysis.frames))
    with TableWriter(out_dir) as tables, PictureWriter(analysis, out_dir, observer, enabled=draw) as pictures:
        for position, (frame, image) in enumerate(zip(analysis.frames, images, strict=False)):
            result = None
            if calibration is not None:
                result = measure_people(frame.people, calibration, distance_threshold_m=threshold_m).result
                analysis.tally(result)
            tables.write(frame_record(analysis, position, frame, result))
            if image is not None and result is not None:
                pictures.draw(image, frame, result)
            observer.advance(people=len(frame.people))


def run_analysis(path: Path, out_dir: Path, options: AnalyzeOptions, observer: Observer) -> Analysis:
    """The whole run; AnalyzeError for bad input or a camera that cannot be calibrated (after writing what can be).

    When the calibration fails, calibration.json (with the reason and the evidence) and the people found are
    still written, so the pose work of a long video is not lost; the pictures need a camera and are not drawn.
    """
    options = options.checked()
    source = open_source(path, stride=options.stride, max_frames=options.max_frames, fps=options.fps)
    prepare_output(out_dir)
    estimator = load_estimator(options)

    started = time.perf_counter()
    static_after_s = _static_after_s(options)
    frames, skipped = detect(source, estimator, observer)
    frames = mark_static(frames, static_after_s)
    times = {"pose": time.perf_counter() - started}
    warnings = run_warnings(frames)  # the guided pass reads the same frames, with the same times
    for warning in warnings:
        observer.note(warning)
    if not frames:
        raise AnalyzeError(f"no frame of {path} could be analysed ({len(skipped)} skipped, see the notes above)")

    observer.begin("calibration", 1)
    started = time.perf_counter()
    # Fewer people than --min-people give no camera: none to report, and none to guide a second pass (a rough
    # camera would steer the search wrong).
    evidence, solve = calibrate_frames(frames, source.image_size_px, options, min_people=options.min_people)
    times["calibration"] = time.perf_counter() - started
    observer.advance(people=solve.people_used)
    if options.guided and solve.calibration is not None:
        started = time.perf_counter()
        box = feet_box(frames, source.image_size_px)
        first_people = sum(len(f.people) for f in frames)
        frames, skipped = detect(source, estimator, observer, solve.calibration, box)
        frames = mark_static(frames, static_after_s)
        times["guided"] = time.perf_counter() - started
        observer.begin("calibration", 1)
        started = time.perf_counter()
        evidence, solve = calibrate_frames(frames, source.image_size_px, options, min_people=options.min_people)
        times["calibration"] += time.perf_counter() - started
        observer.advance(people=solve.people_used)
        observer.note(
            f"guided pass: {sum(len(f.people) for f in frames)} people found (first pass {first_people}), "
            f"{len(evidence)} usable"
        )
    analysis = Analysis(
        source=source,
        options=options,
        pose_model=estimator.name,
        frames=frames,
        skipped=skipped,
        evidence=evidence,
        solve=solve,
        roles=roles_of(evidence, solve),
        times_s=times,
        warnings=warnings,
    )
    write_calibration(analysis, out_dir)
    started = time.perf_counter()
    report_frames(analysis, out_dir, observer)
    times["results"] = time.perf_counter() - started
    if solve.calibration is None:
        raise AnalyzeError(_calibration_failure(analysis, out_dir))
    return analysis


# A folder of images without --fps: linking (service.geometry.tracks) and the static spots need the frames' times.
NO_TIMES_WARNING = (
    "the images have no times (give --fps, the rate they were taken at): a person seen in several images counts as "
    "several people, so the sigma is too small where people repeat (on simulated cameras the normal was within 2 "
    "sigma on 86 % instead of 95 %), and no spot can be found static"
)


def run_warnings(frames: Sequence[AnalyzedFrame]) -> list[str]:
    """What the run cannot do with these frames, and what that costs the answer."""
    if len(frames) > 1 and any(frame.time_s is None for frame in frames):
        return [NO_TIMES_WARNING]
    return []


def _calibration_failure(analysis: Analysis, out_dir: Path) -> str:
    usable = len(analysis.evidence)
    frames = len(analysis.frames)
    if usable == 0:
        what = "no usable people" if analysis.people_seen else "no people"
        detail = f"{what} found in {frames} frames"
    else:
        detail = f"{analysis.solve.error} ({usable} usable people from {frames} frames)"
    return f"calibration failed: {detail}; the people found are in {out_dir / 'frames.jsonl'}"


def _static_after_s(options: AnalyzeOptions) -> float:
    from service.settings import get_settings

    return get_settings().static_after_s if options.static_after_s is None else options.static_after_s


def load_estimator(options: AnalyzeOptions) -> PoseEstimator:
    """The service's pose estimator with this run's model (settings: model directory, threads, detector size)."""
    from service.pose.model_files import ModelFilesError
    from service.pose.pipeline import load_pose_estimator
    from service.settings import get_settings

    update: dict[str, object] = {}
    if options.pose_model is not None:
        update["pose_model"] = options.pose_model
    if options.model_dir is not None:
        update["model_dir"] = options.model_dir
    if options.detector_input_px is not None:
        update["detector_input_px"] = options.detector_input_px
    try:
        return load_pose_estimator(get_settings().model_copy(update=update))
    except ModelFilesError as exc:
        raise AnalyzeError(str(exc)) from None
