"""Detection recall on real frames, per detector policy: `posemetry bench recall`.

Two views, two kinds of truth:
- Oxford Town Centre clip frames (`clip_NNNNNN.jpg` is frame NNNNNN of the upstream video) against the upstream
  manual body boxes (`TownCentre-groundtruth.top`), for the people whose annotated box lies fully in the frame, by
  annotated height. The annotation lags the clip: the median IoU of detections with the boxes of the same frame
  number is 0.59, peaking at 0.76 with the boxes of five frames earlier (measured over all 22 clip frames), and
  it is amodal (a man behind a sign board is boxed to his hidden feet). So a person counts as found when a
  detection overlaps one of their boxes of frames n-5..n with IoU >= 0.5 (`strict`), and, in the `visible`
  column, also when a detection boxes the visible part of them: it holds the annotated head and lies at least
  80 % inside the annotated body box. Matching is one-to-one (greedy by overlap). The annotation misses some
  people (mannequins are not annotated either), so unmatched detections are not all false positives.
  The detector's settings were chosen on those 22 frames; the clip's other 104 frames (decoded from
  `TownCentreXVID_clip126.mp4`, when it is there) are reported apart, as a check on frames nothing was tuned on.
  They are the same five seconds of street, so they test the tuning, not another camera.
- mot3d atrium frames (steep, wide-angle, 50-90 px people, seated people at a table) against a small annotation
  made by eye (`tests/pose/data/atrium_annotations.json`: head pixel and posture of every person on the floor of
  six frames): a person is found when one detection holds their head (one-to-one, by distance to the box's top
  centre). For every atrium frame, annotated or not, the number of people found.

Policies: `plain` (the frame letterboxed to 640 px, the detector as it was), `uncalibrated` (the pipeline's
policy for a camera's first frame without a calibration), `later` (its policy for an uncalibrated camera's later
frames: sized by the usable people of the view's frames this policy ran on before), `calibrated` (the pipeline
guided by a calibration: Town Centre's published one; the atrium's only with `--atrium-calibration`, a
calibration.json written by `posemetry analyze`). Detector CPU time is the process's (all threads) per frame, with
the plan's detector input in megapixels (time is linear in it).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path
from typing import Final

import numpy as np
from scipy.optimize import linear_sum_assignment

from service.geometry import DEFAULT_HEIGHT_M, Calibration
from service.pose.merge import inside_fraction, iou_matrix

from .towncentre import Annotation, as_calibration, camera, load_annotations, load_calibration

Progress = Callable[[str], None]
POLICIES: Final = ("plain", "uncalibrated", "later", "calibrated")
LAG_FRAMES: Final = 5
STRICT_IOU: Final = 0.5
VISIBLE_INSIDE: Final = 0.8
SIZE_BINS_PX: Final = ((0.0, 150.0), (150.0, 200.0), (200.0, np.inf))
SIZE_LABELS: Final = ("<150", "150-200", "200+")
HEAD_MARGIN: Final = 0.15
"""An atrium head may lie this fraction of the box height outside it (boxes of people seen from above are tight)."""
FRAME_SIZE: Final = (1920, 1080)
CLIP_VIDEO: Final = "TownCentreXVID_clip126.mp4"


@dataclass(frozen=True)
class TownPerson:
    box: tuple[float, float, float, float]
    lagged: list[tuple[float, float, float, float]]
    """The person's body boxes of frames n-LAG_FRAMES..n."""
    head: tuple[float, float, float, float] | None

    @property
    def height_px(self) -> float:
        return self.box[3] - self.box[1]


def town_truth(annotations: dict[int, list[Annotation]], frame: int) -> list[TownPerson]:
    """The annotated people fully in view in one frame, with their recent boxes."""
    width, height = FRAME_SIZE
    people = []
    for person in annotations.get(frame, []):
        box = person.body_xyxy
        if box is None or box[0] < 0 or box[1] < 0 or box[2] > width or box[3] > height:
            continue
        lagged = [
            other.body_xyxy
            for offset in range(-LAG_FRAMES, 1)
            for other in annotations.get(frame + offset, [])
            if other.person == person.person and other.body_xyxy is not None
        ]
        people.append(TownPerson(box, lagged, person.head_xyxy))
    return people


def _greedy(score: np.ndarray, threshold: float) -> np.ndarray:
    """(people,) bool: one-to-one matching of people (rows) and detections (columns), best scores first."""
    hit = np.zeros(score.shape[0], dtype=bool)
    used: set[int] = set()
    for flat in np.argsort(-score, axis=None):
        i, j = divmod(int(flat), score.shape[1])
        if score[i, j] < threshold:
            break
        if not hit[i] and j not in used:
            hit[i] = True
            used.add(j)
    return hit


def match_town(people: Sequence[TownPerson], boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(strict, visible) hits per person (see the module docstring)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if not people or not len(boxes):
        return np.zeros(len(people), dtype=bool), np.zeros(len(people), dtype=bool)
    overlap = np.array([iou_matrix(np.array(p.lagged), boxes).max(axis=0) for p in people])
    strict = _greedy(overlap, STRICT_IOU)
    visible_score = overlap.copy()
    for i, person in enumerate(people):
        if person.head is None:
            continue
        grown = np.array(person.box) + np.array([-1, -1, 1, 1]) * 0.1 * person.height_px
        inside = inside_fraction(boxes, grown[None])[:, 0]
        hx, hy = (person.head[0] + person.head[2]) / 2, (person.head[1] + person.head[3]) / 2
        holds_head = (boxes[:, 0] <= hx) & (hx <= boxes[:, 2]) & (boxes[:, 1] <= hy) & (hy <= boxes[:, 3])
        visible_score[i] = np.where((inside >= VISIBLE_INSIDE) & holds_head, np.maximum(overlap[i], 1.0), overlap[i])
    return strict, _greedy(visible_score, STRICT_IOU)


def match_atrium(people: Sequence[dict], boxes: np.ndarray) -> tuple[np.ndarray, int]:
    """(hit per annotated person, detections matching nobody, uncertain people excluded from both)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    heads = np.array([p["head"] for p in people], dtype=np.float64).reshape(-1, 2)
    cost = np.full((len(people), len(boxes)), np.inf)
    for j, (left, top, right, bottom) in enumerate(boxes):
        margin = HEAD_MARGIN * (bottom - top)
        inside = (heads[:, 0] >= left - margin) & (heads[:, 0] <= right + margin)
        inside &= (heads[:, 1] >= top - margin) & (heads[:, 1] <= bottom + margin)
        distance = np.hypot(
            (heads[:, 0] - (left + right) / 2) / max(right - left, 1.0), (heads[:, 1] - top) / max(bottom - top, 1.0)
        )
        cost[inside, j] = distance[inside]
    hit = np.zeros(len(people), dtype=bool)
    used = np.zeros(len(boxes), dtype=bool)
    if len(people) and len(boxes):
        finite = np.where(np.isfinite(cost), cost, 1e9)
        for i, j in zip(*linear_sum_assignment(finite), strict=True):
            if np.isfinite(cost[i, j]):
                hit[i], used[j] = True, True
    return hit, int((~used).sum())


@dataclass
class TownTally:
    """Town Centre people found by one policy on one set of frames."""

    people: list[float] = field(default_factory=list)
    """Annotated height of each person."""
    strict: list[bool] = field(default_factory=list)
    visible: list[bool] = field(default_factory=list)
    unmatched: int = 0
    frames: int = 0
    cpu_s: list[float] = field(default_factory=list)
    pixels: list[int] = field(default_factory=list)

    def add(self, people: Sequence[TownPerson], boxes: np.ndarray, pixels: int, cpu_s: float) -> None:
        strict, visible = match_town(people, boxes)
        self.people += [p.height_px for p in people]
        self.strict += strict.tolist()
        self.visible += visible.tolist()
        self.unmatched += len(boxes) - int(strict.sum())
        self.frames += 1
        self.pixels.append(pixels)
        self.cpu_s.append(cpu_s)

    def recall(self, lo: float = 0.0, hi: float = np.inf, *, visible: bool = False) -> tuple[int, int]:
        heights = np.array(self.people)
        hits = np.array(self.visible if visible else self.strict, dtype=bool)
        chosen = (heights >= lo) & (heights < hi)
        return int(hits[chosen].sum()), int(chosen.sum())


@dataclass
class PolicyResult:
    policy: str
    town: TownTally = field(default_factory=TownTally)
    """The 22 clip frames the settings were chosen on."""
    clip: TownTally = field(default_factory=TownTally)
    """The clip's other frames (decoded from the video)."""
    atrium_hits: dict[str, list[int]] = field(default_factory=lambda: {"standing": [0, 0], "seated": [0, 0]})
    atrium_unmatched: int = 0
    atrium_found: dict[str, int] = field(default_factory=dict)
    """People found per atrium frame (file name -> count)."""
    atrium_cpu_s: list[float] = field(default_factory=list)
    atrium_pixels: list[int] = field(default_factory=list)


@dataclass
class RecallBenchmark:
    results: list[PolicyResult]
    town_frames: int
    atrium_frames: int
    annotated_atrium_frames: int
    atrium_calibrated: bool
    load: tuple[float, float, float]


def other_clip_frames(video: Path, skip: set[int], limit: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """(frame number, image) of the clip video's frames not in `skip`, in order; at most `limit`, evenly spread.
    Nothing when the video is not there."""
    import cv2

    if not video.is_file() or limit == 0:
        return
    capture = cv2.VideoCapture(str(video))
    try:
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        wanted = [number for number in range(count) if number not in skip]
        if limit is not None and limit < len(wanted):
            wanted = [wanted[round(k * (len(wanted) - 1) / max(limit - 1, 1))] for k in range(limit)]
        chosen = set(wanted)
        for number in range(max(wanted, default=-1) + 1):
            ok, image = capture.read()
            if not ok:
                raise OSError(f"{video} ends at frame {number}, before the {count} frames it declares")
            if number in chosen:
                yield number, image
    finally:
        capture.release()


def _read(path: Path) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path))
    if image is None:
        raise OSError(f"cannot read {path}")
    return image


def load_atrium_annotation(path: Path) -> dict[str, list[dict]]:
    """File name -> annotated people ({"head": [x, y], "posture": ...})."""
    return json.loads(Path(path).read_text())["frames"]


def calibration_from_json(path: Path, height_m: float | None = None) -> Calibration:
    """A calibration.json written by `posemetry analyze`, as the geometry's Calibration."""
    data = json.loads(Path(path).read_text())
    height = height_m or data.get("options", {}).get("height_m", DEFAULT_HEIGHT_M)
    normal = np.asarray(data["normal"], dtype=np.float64)
    return camera(data["fx_px"], data["fy_px"], data["cx_px"], data["cy_px"], normal, data["rho_m"], FRAME_SIZE, height)


def run_recall_benchmark(
    model_dir: Path,
    town_dir: Path,
    atrium_dir: Path,
    atrium_annotation: Path,
    policies: Sequence[str] = POLICIES,
    progress: Progress = lambda _message: None,
    *,
    atrium_calibration: Path | None = None,
    threads: int | None = None,
    clip_frames: int | None = None,
) -> RecallBenchmark:
    """Detect with each policy on every Town Centre clip frame and every atrium frame, and match to the truth.

    `clip_frames`: how many of the clip video's other frames to check as well (evenly spread; default all, 0 none).
    """
    import os

    from service.frames.detection import SEEN_FRAMES
    from service.frames.keypoints import people_from_detections
    from service.pose.pipeline import TopDownPose
    from service.pose.regions import uncalibrated_plan

    estimator = TopDownPose(model_dir, "lightning", threads=threads)
    detector = estimator.detector
    annotations = load_annotations(town_dir / "TownCentre-groundtruth.top")
    town_paths = sorted((town_dir / "frames").glob("clip_*.jpg"))
    atrium_paths = sorted(Path(atrium_dir).glob("*.jpg"))
    if not town_paths or not atrium_paths:
        raise FileNotFoundError(f"no frames in {town_dir / 'frames'} or {atrium_dir}")
    truth = load_atrium_annotation(atrium_annotation)
    town_cal = as_calibration(load_calibration(town_dir / "TownCentre-calibration-ci.txt"))
    atrium_cal = calibration_from_json(atrium_calibration) if atrium_calibration is not None else None

    seen: list[list[tuple[float, float, float, float]]] = []  # usable boxes of the view's `later` frames

    def detect(policy: str, image: np.ndarray, calibration: Calibration | None):
        """(detections, detector input pixels, detection CPU seconds) of one policy, None when it cannot run (no
        calibration)."""
        start = time.process_time()
        if policy == "later":
            boxes = np.array([box for people in seen[-SEEN_FRAMES:] for box in people]).reshape(-1, 4)
            detections, times = estimator.detect(image, seen_boxes_px=boxes)
            cpu_s = time.process_time() - start
            # The frame's usable people for the next ones (untimed: pose is not detection).
            people = people_from_detections(estimator(image, seen_boxes_px=boxes), (image.shape[1], image.shape[0]))
            seen.append([p.box_px for p in people if p.box_px is not None and p.unusable_reason is None])
            return detections, sum(region.input_pixels for region in times.regions), cpu_s
        if policy == "plain":
            plan = uncalibrated_plan((image.shape[1], image.shape[0]), (1 / 3,), base_input_px=detector.input_px)
            detections, times = detector.detect(image, plan)
        elif policy == "uncalibrated" or calibration is not None:
            detections, times = estimator.detect(image, calibration if policy == "calibrated" else None)
        else:
            return None
        return detections, sum(region.input_pixels for region in times.regions), time.process_time() - start

    results = []
    for policy in policies:
        result = PolicyResult(policy)
        progress(f"{policy}: {len(town_paths)} Town Centre frames, {len(atrium_paths)} atrium frames")
        seen.clear()
        numbers = [int(path.stem.split("_")[1]) for path in town_paths]
        town = ((number, _read(path), result.town) for number, path in zip(numbers, town_paths, strict=True))
        others = other_clip_frames(town_dir / CLIP_VIDEO, set(numbers), clip_frames)
        for number, image, tally in chain(town, ((number, image, result.clip) for number, image in others)):
            found = detect(policy, image, town_cal)
            assert found is not None
            detections, pixels, cpu_s = found
            tally.add(town_truth(annotations, number), detections.boxes_xyxy_px, pixels, cpu_s)
        seen.clear()
        for path in atrium_paths:
            image = _read(path)
            found = detect(policy, image, atrium_cal)
            if found is None:
                break
            detections, pixels, cpu_s = found
            result.atrium_cpu_s.append(cpu_s)
            result.atrium_pixels.append(pixels)
            result.atrium_found[path.name] = len(detections.scores)
            people = [p for p in truth.get(path.name, []) if p["posture"] in result.atrium_hits]
            if path.name in truth:
                hit, _ = match_atrium(people, detections.boxes_xyxy_px)
                everyone = truth[path.name]
                _, unmatched = match_atrium(everyone, detections.boxes_xyxy_px)
                result.atrium_unmatched += unmatched
                for posture, tally in result.atrium_hits.items():
                    chosen = [i for i, p in enumerate(people) if p["posture"] == posture]
                    tally[0] += int(hit[chosen].sum())
                    tally[1] += len(chosen)
        results.append(result)
    return RecallBenchmark(
        results=results,
        town_frames=len(town_paths),
        atrium_frames=len(atrium_paths),
        annotated_atrium_frames=sum(p.name in truth for p in atrium_paths),
        atrium_calibrated=atrium_cal is not None,
        load=os.getloadavg(),
    )


def _ratio(pair: tuple[int, int] | list[int]) -> str:
    hit, total = pair
    return f"{hit}/{total} = {100 * hit / total:.1f} %" if total else "-"


def _town_lines(results: Sequence[PolicyResult], tally_of: Callable[[PolicyResult], TownTally]) -> list[str]:
    bins = ", ".join(SIZE_LABELS)
    lines = [f"  {'policy':<13} {'strict all':>19} {'visible all':>19}   by height ({bins} px, strict)"]
    for r in results:
        tally = tally_of(r)
        by_size = "  ".join(_ratio(tally.recall(lo, hi)) for lo, hi in SIZE_BINS_PX)
        cost = f"{np.mean(tally.pixels) / 1e6:.2f} MPx, detector {1000 * np.mean(tally.cpu_s):.0f} ms CPU/frame"
        lines.append(
            f"  {r.policy:<13} {_ratio(tally.recall()):>19} {_ratio(tally.recall(visible=True)):>19}   {by_size}"
            f"   unmatched {tally.unmatched / max(tally.frames, 1):.1f}/frame; {cost}"
        )
    return lines


def recall_lines(result: RecallBenchmark) -> list[str]:
    """The report as printable lines (terminal and docs alike)."""
    one, five, fifteen = result.load
    lines = [
        f"detection recall: RTMDet-nano per detector policy; {result.town_frames} Town Centre clip frames, "
        f"{result.atrium_frames} atrium frames ({result.annotated_atrium_frames} annotated); load average "
        f"{one:.2f} {five:.2f} {fifteen:.2f}",
        "Town Centre, annotated people fully in view (strict: IoU >= 0.5 with one of their boxes of the last 5 "
        "frames; visible: or the detection boxes their visible part):",
    ]
    lines += _town_lines(result.results, lambda r: r.town)
    if any(r.clip.frames for r in result.results):
        frames = max(r.clip.frames for r in result.results)
        lines.append(f"Town Centre, {frames} other frames of the clip (from the video; no setting was chosen on them):")
        lines += _town_lines(result.results, lambda r: r.clip)
    lines.append("mot3d atrium, annotated people on the floor (a detection holds their head):")
    for r in result.results:
        if not r.atrium_found:
            lines.append(f"  {r.policy:<13} (no atrium calibration given: --atrium-calibration)")
            continue
        cost = f"{np.mean(r.atrium_pixels) / 1e6:.2f} MPx, detector {1000 * np.mean(r.atrium_cpu_s):.0f} ms CPU/frame"
        lines.append(
            f"  {r.policy:<13} standing {_ratio(r.atrium_hits['standing'])}, seated {_ratio(r.atrium_hits['seated'])},"
            f" unmatched detections {r.atrium_unmatched}; {cost}"
        )
    counted = [r for r in result.results if r.atrium_found]
    if not counted:
        return lines
    lines.append("people found per atrium frame:")
    names = list(counted[0].atrium_found)
    lines.append(f"  {'policy':<13} {'mean':>5}  " + " ".join(name[-9:-4] for name in names))
    for r in counted:
        counts = [r.atrium_found[name] for name in names]
        lines.append(f"  {r.policy:<13} {np.mean(counts):5.1f}  " + " ".join(f"{c:5d}" for c in counts))
    return lines
