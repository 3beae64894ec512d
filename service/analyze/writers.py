"""The files a run writes, besides pictures: calibration.json, frames.jsonl and three CSV tables.

frames.jsonl has everything (one frame per line, each person with keypoints, verdict and position, every pair);
the CSVs are the same numbers flattened for spreadsheets: people.csv (a row per person per frame), pairs.csv (a
row per pair per frame) and frames.csv (a row per frame: counts and the closest pair). Empty cells are unknowns
(a person who could not be placed, a pair involving one).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from service import __version__
from service.domain import METRES_PER_FOOT
from service.frames.schemas import FrameResult, PairDistance
from service.geometry import Quality
from service.geometry.uncertainty import CANONICAL_PARAMETERS

from .analysis import Analysis, AnalyzedFrame
from .errors import AnalyzeError
from .records import (
    CalibrationRecord,
    CalibrationUncertaintyRecord,
    EvidenceRecord,
    FrameRecord,
    PairRecord,
    PersonRecord,
    QualityRecord,
    SourceRecord,
)

CALIBRATION_FILE = "calibration.json"
FRAMES_FILE = "frames.jsonl"
PEOPLE_CSV = "people.csv"
PAIRS_CSV = "pairs.csv"
FRAMES_CSV = "frames.csv"
OVERLAY_DIR = "overlays"
TOPDOWN_DIR = "topdown"
OVERLAY_VIDEO = "overlay.mp4"
TOPDOWN_VIDEO = "topdown.mp4"
PICTURE_SUFFIXES = frozenset({".png", ".jpg"})

PEOPLE_COLUMNS = (
    "frame",
    "time_s",
    "file",
    "person",
    "detection_score",
    "box_left_px",
    "box_top_px",
    "box_right_px",
    "box_bottom_px",
    "shoulder_x_px",
    "shoulder_y_px",
    "ankle_x_px",
    "ankle_y_px",
    "posture",
    "usable",
    "unusable_reason",
    "calibration",
    "placed_from",
    "ground_right_m",
    "ground_forward_m",
    "nearest_person",
    "nearest_m",
    "in_violation",
)
PAIRS_COLUMNS = ("frame", "time_s", "file", "i", "j", "distance_m", "distance_std_m", "distance_ft", "violation")
FRAMES_COLUMNS = ("frame", "time_s", "file", "people", "usable", "placed", "pairs", "violations", "closest_m")


def prepare_output(out_dir: Path) -> None:
    """Create the output folder (and check it is writable) before any work; clear pictures of an earlier run.

    Re-running into the same folder replaces the earlier run's files; the pictures in `overlays/` and `topdown/`
    (folders this command owns) are deleted first, so a shorter re-run leaves no stale frames behind.
    """
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / ".posemetry-write-test"
        probe.write_bytes(b"")
        probe.unlink()
        for folder in (OVERLAY_DIR, TOPDOWN_DIR):
            for stale in (out_dir / folder).glob("*.*"):
                if stale.suffix in PICTURE_SUFFIXES and stale.is_file():
                    stale.unlink()
    except OSError as exc:
        raise AnalyzeError(f"cannot write to {out_dir}: {exc.strerror or exc}") from None


def _finite(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def calibration_record(analysis: Analysis) -> CalibrationRecord:
    cal, solve, options, source = analysis.calibration, analysis.solve, analysis.options, analysis.source
    evidence = EvidenceRecord(
        frames=len(analysis.frames),
        frames_skipped=len(analysis.skipped),
        people_seen=analysis.people_seen,
        usable=len(analysis.evidence),
        unusable_reasons=analysis.unusable_reasons(),
        used=solve.people_used,
        inliers=0 if cal is None else cal.num_inliers,
    )
    common = {
        "evidence": evidence,
        "image_size_px": source.image_size_px,
        "person_height_m": options.height_m,
        "pose_model": analysis.pose_model,
        "source": SourceRecord(path=str(source.path), kind=source.kind, fps=source.fps, stride=source.stride),
        "options": options.as_record(),
        "duration_s": analysis.times_s.get("calibration", 0.0),
        "posemetry_version": __version__,
        "warnings": analysis.warnings,
    }
    if cal is None:
        return CalibrationRecord(status="failed", reason=solve.error or "no usable people", **common)
    normal = np.asarray(cal.normal, dtype=float)
    unc = cal.uncertainty
    return CalibrationRecord(
        status="ok",
        fx_px=cal.fx,
        fy_px=cal.fy,
        cx_px=cal.cx,
        cy_px=cal.cy,
        normal=(float(normal[0]), float(normal[1]), float(normal[2])),
        rho_m=cal.rho,
        tilt_deg=float(np.degrees(np.arcsin(np.clip(-normal[2], -1.0, 1.0)))),
        roll_deg=float(np.degrees(np.arctan2(normal[0], -normal[1]))),
        distortion_k=cal.distortion_k,
        lens_coefficients=None if cal.lens is None else cal.lens.coefficients,
        camera_height_m=cal.camera_height_m,
        principal_point_source=cal.principal_point_source,
        focal_source=cal.focal_source,
        distortion_source=cal.distortion_source,
        individuals=cal.individuals,
        quality=None if cal.quality is None else _quality_record(cal.quality),
        uncertainty=None
        if unc is None
        else CalibrationUncertaintyRecord(
            fx_std_px=unc.fx_px,
            fy_std_px=unc.fy_px,
            normal_std_deg=unc.normal_deg,
            rho_std_m=unc.rho_m,
            cx_std_px=unc.cx_px,
            cy_std_px=unc.cy_px,
            noise_px=unc.noise_px,
            noise_per_length=unc.noise_per_length,
            covariance=np.asarray(unc.covariance, dtype=float).tolist(),
            covariance_parameters=list(CANONICAL_PARAMETERS),
        ),
        reprojection_rms_px=_finite(cal.reprojection_rms_px),
        **common,
    )


def _quality_record(quality: Quality) -> QualityRecord:
    return QualityRecord(
        grade=quality.grade,
        distance_2sigma_m=_finite(quality.distance_2sigma_m),
        typical_range_m=_finite(quality.typical_range_m),
        reasons=list(quality.reasons),
        advice=list(quality.advice),
        people_needed=quality.people_needed,
    )


def nearest(pairs: Sequence[PairDistance], index: int) -> tuple[int | None, float | None]:
    """(the nearest placed neighbour, its distance) of person `index`, from the frame's pairs."""
    best: tuple[int | None, float | None] = (None, None)
    for pair in pairs:
        if pair.distance_m is None or index not in (pair.i, pair.j):
            continue
        if best[1] is None or pair.distance_m < best[1]:
            best = (pair.j if pair.i == index else pair.i, pair.distance_m)
    return best


def _rounded(values: Iterable[float], digits: int) -> tuple[float, ...]:
    return tuple(round(float(v), digits) for v in values)


def frame_record(analysis: Analysis, position: int, frame: AnalyzedFrame, result: FrameResult | None) -> FrameRecord:
    """A frame's line of frames.jsonl: its people, their part in the calibration and, when measured, the pairs.

    Pixels are rounded to 0.01 px and scores to 1e-4: pose models are not more precise, and the lines stay short.
    """
    threshold_m = analysis.options.threshold_m
    pairs = result.pairs if result is not None else []
    positions = {p.index: p for p in result.people} if result is not None else {}
    in_violation = {index for pair in (result.violations if result else []) for index in (pair.i, pair.j)}
    people = []
    for index, person in enumerate(frame.people):
        placed = positions.get(index)
        nearest_index, nearest_m = nearest(pairs, index)
        people.append(
            PersonRecord(
                index=index,
                box_px=None if person.box_px is None else _rounded(person.box_px, 2),  # type: ignore[arg-type]
                detection_score=None if person.detection_score is None else round(person.detection_score, 4),
                keypoints=None
                if person.keypoints is None
                else [(*_rounded(k[:2], 2), round(float(k[2]), 4)) for k in person.keypoints],  # type: ignore[misc]
                shoulder_px=person.shoulder_px,
                ankle_px=person.ankle_px,
                posture=person.posture,
                usable=person.unusable_reason is None,
                unusable_reason=person.unusable_reason,
                calibration=analysis.roles.get((position, index)),
                placed_from=None if placed is None else placed.placed_from,
                ground_m=None if placed is None else placed.ground_m,
                point_m=None if placed is None else placed.point_m,
                nearest_index=nearest_index,
                nearest_m=nearest_m,
                in_violation=index in in_violation,
            )
        )
    pair_records = [
        PairRecord(
            i=p.i,
            j=p.j,
            distance_m=p.distance_m,
            distance_std_m=p.distance_std_m,
            violation=p.distance_m is not None and p.distance_m < threshold_m,
        )
        for p in pairs
    ]
    return FrameRecord(
        frame=frame.index,
        time_s=frame.time_s,
        file=frame.file,
        people=people,
        pairs=pair_records,
        violations=sum(p.violation for p in pair_records),
    )


def _cell(value: object) -> object:
    """CSV cell: empty for unknown, rounded floats (micro-units are noise), booleans as true/false."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}" if abs(value) < 1e4 else f"{value:.2f}"
    return value


def _people_rows(record: FrameRecord) -> Iterable[Sequence[object]]:
    for p in record.people:
        box = p.box_px or (None, None, None, None)
        shoulder = p.shoulder_px or (None, None)
        ankle = p.ankle_px or (None, None)
        ground = p.ground_m or (None, None)
        yield (
            record.frame,
            record.time_s,
            record.file,
            p.index,
            p.detection_score,
            *box,
            *shoulder,
            *ankle,
            p.posture,
            p.usable,
            p.unusable_reason,
            p.calibration,
            p.placed_from,
            *ground,
            p.nearest_index,
            p.nearest_m,
            p.in_violation,
        )


def _pairs_rows(record: FrameRecord) -> Iterable[Sequence[object]]:
    for p in record.pairs:
        feet = None if p.distance_m is None else p.distance_m / METRES_PER_FOOT
        yield (record.frame, record.time_s, record.file, p.i, p.j, p.distance_m, p.distance_std_m, feet, p.violation)


def _frame_row(record: FrameRecord) -> Sequence[object]:
    distances = [p.distance_m for p in record.pairs if p.distance_m is not None]
    return (
        record.frame,
        record.time_s,
        record.file,
        len(record.people),
        sum(p.usable for p in record.people),
        sum(p.ground_m is not None for p in record.people),
        len(record.pairs),
        record.violations,
        min(distances, default=None),
    )


def write_calibration(analysis: Analysis, out_dir: Path) -> Path:
    path = out_dir / CALIBRATION_FILE
    path.write_text(calibration_record(analysis).model_dump_json(indent=2) + "\n")
    return path


class TableWriter:
    """frames.jsonl and the CSVs, written a frame at a time (a context manager: the files are closed on exit)."""

    def __init__(self, out_dir: Path) -> None:
        self._files = [
            (out_dir / name).open("w", newline="") for name in (FRAMES_FILE, PEOPLE_CSV, PAIRS_CSV, FRAMES_CSV)
        ]
        self._jsonl = self._files[0]
        self._people, self._pairs, self._frames = (csv.writer(f) for f in self._files[1:])
        for writer, columns in (
            (self._people, PEOPLE_COLUMNS),
            (self._pairs, PAIRS_COLUMNS),
            (self._frames, FRAMES_COLUMNS),
        ):
            writer.writerow(columns)

    def __enter__(self) -> TableWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        for handle in self._files:
            handle.close()

    def write(self, record: FrameRecord) -> None:
        self._jsonl.write(record.model_dump_json() + "\n")
        for rows, writer in ((_people_rows(record), self._people), (_pairs_rows(record), self._pairs)):
            writer.writerows([_cell(v) for v in row] for row in rows)
        self._frames.writerow([_cell(v) for v in _frame_row(record)])
