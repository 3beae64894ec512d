"""Where the detector's box would place a person, against where their ankles place them (Town Centre, issue 17).

Input: a `posemetry analyze` run's `frames.jsonl` on the Oxford Town Centre clip. Every person placed from trusted
ankles whose box is clean (service.frames.keypoints.box_bottom_problem: not cut by the frame, not inside another
person's box) is a sample: their ankle centre, put on the street by the published camera, is the truth; the cues
are put on the street by the same camera:

- `box bottom`: the box's bottom centre, moved up by the median offset between box bottom and ankle centre (a
  fraction of the box height), on the ankles' plane;
- `shoulders`: the shoulder centre on the plane raised by the height prior (what a `partial` person gets);
- `box top`: the box's top centre on the plane raised by the median head-top height measured here.

The offsets are reported as fractions of the box height (bias and spread), the ground errors in metres by person
height in pixels. Run: `python -m bench.placement RUN/frames.jsonl` (needs the shared data); with `pairs` after it,
the run's pair distances with a box-placed person against the same pixels under the published camera; with
`annotation`, the share of the run's placed people that are annotated pedestrians (upstream body boxes).
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bench.towncentre import Annotation, load_annotations, load_calibration
from service.frames.keypoints import box_bottom_problem
from service.pose.merge import iou_matrix

CALIBRATION = Path(__file__).resolve().parents[1] / "../shared/data/oxford_town_centre/TownCentre-calibration-ci.txt"
HEIGHT_PRIOR_M = 1.32
SIZE_BINS_PX = ((0.0, 150.0), (150.0, 220.0), (220.0, 1e9))


def _plane_points(town: object, pixels: np.ndarray, lift_m: float | np.ndarray) -> np.ndarray:
    """Pinhole rays of the published camera meeting the street raised by `lift_m`, lowered back onto the street."""
    xy = np.c_[(pixels[:, 0] - town.cx) / town.fx, (pixels[:, 1] - town.cy) / town.fy]  # type: ignore[attr-defined]
    rays = np.c_[xy, np.ones(len(xy))]
    normal = town.ground_normal  # type: ignore[attr-defined]
    depth = -(town.ground_rho - lift_m) / (rays @ normal)  # type: ignore[attr-defined]
    return rays * depth[:, None] - np.asarray(lift_m).reshape(-1, 1) * normal


def _head_heights(town: object, ankles_m: np.ndarray, tops_px: np.ndarray) -> np.ndarray:
    """Height of the box top above the ankle point: closest approach of its ray to the vertical through the ankle."""
    normal = town.ground_normal  # type: ignore[attr-defined]
    xy = np.c_[(tops_px[:, 0] - town.cx) / town.fx, (tops_px[:, 1] - town.cy) / town.fy]  # type: ignore[attr-defined]
    ray = np.c_[xy, np.ones(len(xy))]
    nr, rr, nx, rx = ray @ normal, np.sum(ray * ray, 1), ankles_m @ normal, np.sum(ray * ankles_m, 1)
    return (-nx * rr + nr * rx) / (rr - nr * nr) + nx * 0.0


def samples(frames_jsonl: Path) -> dict[str, np.ndarray]:
    """Per clean, ankle-placed person: box, ankle centre, shoulder centre (NaN when not trusted)."""
    boxes, ankles, shoulders = [], [], []
    for line in frames_jsonl.read_text().splitlines():
        frame = json.loads(line)
        people = frame["people"]
        all_boxes = [p["box_px"] for p in people if p["box_px"] is not None]
        for person in people:
            if person["placed_from"] != "ankles" or person["box_px"] is None or person["ankle_px"] is None:
                continue
            if person["unusable_reason"] and person["unusable_reason"].startswith("static"):
                continue
            others = [b for b in all_boxes if b != person["box_px"]]
            if box_bottom_problem(person["box_px"], others, (1920, 1080)) is not None:
                continue
            boxes.append(person["box_px"])
            ankles.append(person["ankle_px"])
            shoulders.append(person["shoulder_px"] or (np.nan, np.nan))
    return {"box": np.array(boxes), "ankle": np.array(ankles), "shoulder": np.array(shoulders, dtype=float)}


def report(frames_jsonl: Path) -> str:
    town = load_calibration(CALIBRATION)
    s = samples(frames_jsonl)
    box, ankle, shoulder = s["box"], s["ankle"], s["shoulder"]
    height_px = box[:, 3] - box[:, 1]
    centre_x = (box[:, 0] + box[:, 2]) / 2
    dy = (box[:, 3] - ankle[:, 1]) / height_px
    dx = (centre_x - ankle[:, 0]) / height_px
    bias = float(np.median(dy))
    lines = [
        f"{len(box)} clean ankle-placed people; box bottom - ankle centre, fraction of box height:",
        f"  dy median {bias:.4f}, MAD*1.48 {1.4826 * np.median(np.abs(dy - bias)):.4f}, "
        f"p10/p90 {np.percentile(dy, 10):.4f}/{np.percentile(dy, 90):.4f}",
        f"  dx median {np.median(dx):.4f}, MAD*1.48 {1.4826 * np.median(np.abs(dx - np.median(dx))):.4f}",
    ]
    truth = _plane_points(town, ankle, 0.0)
    bottom_px = np.c_[centre_x, box[:, 3] - bias * height_px]
    tops_px = np.c_[centre_x, box[:, 1]]
    head_m = _head_heights(town, truth, tops_px)
    head_prior = float(np.median(head_m))
    lines.append(
        f"  box top above the ankle centre: median {head_prior:.3f} m, MAD*1.48 "
        f"{1.4826 * np.median(np.abs(head_m - head_prior)):.3f} m ({head_prior / HEIGHT_PRIOR_M:.3f} of the prior)"
    )
    cues = {
        "box bottom": _plane_points(town, bottom_px, 0.0),
        "shoulders": _plane_points(town, shoulder, HEIGHT_PRIOR_M),
        "box top": _plane_points(town, tops_px, head_prior),
    }
    forward = np.array([0.0, 0.0, 1.0]) - town.ground_normal[2] * town.ground_normal
    forward /= np.linalg.norm(forward)
    lines.append("cue | person px | n | depth bias m | abs error p50 m | p90 m")
    for name, placed in cues.items():
        error = placed - truth
        along = error @ forward
        size = np.linalg.norm(error, axis=1)
        for low, high in SIZE_BINS_PX:
            keep = (height_px >= low) & (height_px < high) & np.isfinite(size)
            if keep.sum() < 5:
                continue
            # The pixel error along the image's vertical in box heights: what measure() propagates.
            lines.append(
                f"{name} | {low:.0f}-{high:.0f} | {keep.sum()} | {np.median(along[keep]):+.3f} | "
                f"{np.median(size[keep]):.3f} | {np.percentile(size[keep], 90):.3f}"
            )
    lines.append(_coverage(town, bottom_px, truth, height_px))
    return "\n".join(lines)


def _standing_px(town: object, ground_m: np.ndarray) -> np.ndarray:
    """Shoulder-to-ankle length in pixels of a person of the prior height at each ground point (pinhole)."""
    normal = town.ground_normal  # type: ignore[attr-defined]
    tops = ground_m + HEIGHT_PRIOR_M * normal
    uv = [np.c_[town.fx * p[:, 0] / p[:, 2], town.fy * p[:, 1] / p[:, 2]] for p in (ground_m, tops)]  # type: ignore
    return np.hypot(*(uv[1] - uv[0]).T)


def _coverage(town: object, bottom_px: np.ndarray, truth: np.ndarray, height_px: np.ndarray) -> str:
    """The isotropic pixel sigma (fraction of the standing length) whose ground ellipses hold 68 % of the errors,
    as service.geometry.measure propagates it (chi-square, 2 degrees of freedom: 2.28)."""
    step = 0.01
    base = _plane_points(town, bottom_px, 0.0)
    jac = np.stack([(_plane_points(town, bottom_px + step * e, 0.0) - base) / step for e in np.eye(2)], -1)  # (N, 3, 2)
    length = _standing_px(town, truth)
    error = base - truth
    lines = [f"standing length / box height: median {np.median(length / height_px):.3f}"]
    for fraction in (0.02, 0.03, 0.04, 0.05, 0.06, 0.08):
        cov = (fraction * length)[:, None, None] ** 2 * np.einsum("nik,njk->nij", jac, jac)
        # The ground covariance is rank 2 in 3-D: measure the error in its own plane with the pseudo-inverse.
        m2 = np.einsum("ni,nij,nj->n", error, np.linalg.pinv(cov, rcond=1e-9), error)
        lines.append(f"  sigma {fraction:.2f} x standing length: {np.mean(m2 <= 2.28):.0%} within 1 sigma")
    return "\n".join(lines)


def pairs_report(frames_jsonl: Path, within_m: float = 30.0) -> str:
    """Pairs measured by the run (its own solved camera) against the same pixels under the published camera, for
    the pairs with a box-placed person and, for comparison, the pairs of two ankle-placed people."""
    town = load_calibration(CALIBRATION)
    errors: dict[str, list[float]] = {"box": [], "ankles": []}
    verdicts: dict[str, list[bool]] = {"box": [], "ankles": []}
    relative: dict[str, list[float]] = {"box": [], "ankles": []}
    for line in frames_jsonl.read_text().splitlines():
        people = json.loads(line)["people"]
        pixels = np.array([p["ankle_px"] or (np.nan, np.nan) for p in people], dtype=float).reshape(-1, 2)
        published = _plane_points(town, pixels, 0.0) if len(people) else np.zeros((0, 3))
        for pair in json.loads(line)["pairs"]:
            a, b = people[pair["i"]], people[pair["j"]]
            kinds = {a["placed_from"], b["placed_from"]}
            if pair["distance_m"] is None or not kinds <= {"ankles", "box"}:
                continue
            truth = float(np.linalg.norm(published[pair["i"]] - published[pair["j"]]))
            if not np.isfinite(truth) or truth > within_m:
                continue
            kind = "box" if "box" in kinds else "ankles"
            errors[kind].append(abs(pair["distance_m"] - truth))
            relative[kind].append(abs(pair["distance_m"] - truth) / max(truth, 1e-9))
            verdicts[kind].append((pair["distance_m"] < 1.8288) == (truth < 1.8288))
    lines = ["pairs | n | abs error vs published p50 m | p90 m | relative p50 | 6-ft verdicts agreeing"]
    for kind, values in errors.items():
        if values:
            lines.append(
                f"{kind} | {len(values)} | {np.median(values):.3f} | {np.percentile(values, 90):.3f} | "
                f"{np.median(relative[kind]):.1%} | {np.mean(verdicts[kind]):.1%}"
            )
    return "\n".join(lines)


def _annotated(annotations: dict[int, list[Annotation]], frame: int, box: Sequence[float], lag_frames: int = 5) -> bool:
    """Whether a detection is an annotated pedestrian: IoU >= 0.5 with their body box in frames n-5..n (the
    annotation lags the clip, bench/recall.py), or their head's centre in the top 30 % of the detection."""
    left, top, right, bottom = box
    for number in range(frame - lag_frames, frame + 1):
        for person in annotations.get(number, []):
            if person.body_xyxy is not None and iou_matrix(np.array([box]), np.array([person.body_xyxy]))[0, 0] >= 0.5:
                return True
            if person.head_xyxy is not None:
                x, y = (person.head_xyxy[0] + person.head_xyxy[2]) / 2, (person.head_xyxy[1] + person.head_xyxy[3]) / 2
                if left <= x <= right and top - 10 <= y <= top + 0.3 * (bottom - top):
                    return True
    return False


def annotation_report(frames_jsonl: Path) -> str:
    """Share of the run's placed people that are annotated pedestrians, by placement and by what vouches for them."""
    annotations = load_annotations(CALIBRATION.parent / "TownCentre-groundtruth.top")
    counts: dict[tuple[str, ...], list[int]] = defaultdict(lambda: [0, 0])
    for line in frames_jsonl.read_text().splitlines():
        frame = json.loads(line)
        for person in frame["people"]:
            reason = person["unusable_reason"] or ""
            if person["placed_from"] is None or reason.startswith("static") or person["box_px"] is None:
                continue
            box = person["box_px"]
            key = (
                person["placed_from"],
                "shoulders trusted" if person["shoulder_px"] is not None else "no shoulders",
                "score >= 0.5" if (person["detection_score"] or 0.0) >= 0.5 else "score < 0.5",
                "top cut" if box[1] <= 10.8 else "whole",
            )
            counts[key][0] += 1
            counts[key][1] += _annotated(annotations, frame["frame"], box)
    lines = ["placed from | shoulders | score | box top | n | annotated"]
    for key, (n, hits) in sorted(counts.items()):
        lines.append(f"{' | '.join(key)} | {n} | {hits / n:.0%}")
    return "\n".join(lines)


if __name__ == "__main__":
    mode = sys.argv[2] if len(sys.argv) > 2 else "cues"
    reports = {"cues": report, "pairs": pairs_report, "annotation": annotation_report}
    print(reports[mode](Path(sys.argv[1])))
