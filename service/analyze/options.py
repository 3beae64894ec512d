"""What a user can choose for one `posemetry analyze` run, checked once, recorded in calibration.json."""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from service.domain import feet_to_metres
from service.geometry import DEFAULT_HEIGHT_M, CalibrationProblem, OpenCVLens
from service.pose.model_files import POSE_CHOICES

from .errors import AnalyzeError

Unit = Literal["m", "ft"]
ImageFormat = Literal["png", "jpg"]
DEFAULT_THRESHOLD = "6ft"
# Most usable people one calibration solves on (a spatially balanced sample when there are more), as the
# service's POSEMETRY_CALIBRATION_SAMPLE_CAP: beyond a few thousand the answer stops changing, the time does not.
DEFAULT_SAMPLE_CAP = 2000
# A handful of people pins no focal length; the service waits for this many before its first solve.
DEFAULT_MIN_PEOPLE = 30
_THRESHOLD = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:e[+-]?\d+)?)\s*(m|metres?|meters?|ft|feet|foot)\s*$", re.IGNORECASE)


@dataclass(frozen=True)
class Threshold:
    """A distance threshold as the user wrote it, and in metres."""

    value: float
    unit: Unit

    @property
    def metres(self) -> float:
        return feet_to_metres(self.value) if self.unit == "ft" else self.value

    def __str__(self) -> str:
        return f"{self.value:g} {self.unit}"


def parse_threshold(text: str) -> Threshold:
    """'6ft', '6 ft', '1.8m', '2 metres' -> Threshold; the unit is required (a bare 6 could be either)."""
    match = _THRESHOLD.match(text)
    if not match:
        raise AnalyzeError(f"threshold {text!r} is not a distance with a unit, such as 6ft or 1.8m")
    value = float(match.group(1))
    if not (math.isfinite(value) and 0 < value <= 1000):
        raise AnalyzeError(f"threshold {text!r} must be a positive distance of at most 1000 units")
    unit: Unit = "ft" if match.group(2).lower().startswith("f") else "m"
    return Threshold(value, unit)


def parse_numbers(text: str | None, name: str, counts: tuple[int, ...]) -> tuple[float, ...] | None:
    """'960,540' or '2700' -> floats; None for no text; AnalyzeError naming the option otherwise."""
    if text is None:
        return None
    try:
        values = tuple(float(part) for part in text.replace(" ", "").split(","))
    except ValueError:
        raise AnalyzeError(
            f"{name} must be {' or '.join(map(str, counts))} comma-separated numbers, got {text!r}"
        ) from None
    if len(values) not in counts:
        raise AnalyzeError(f"{name} must be {' or '.join(map(str, counts))} comma-separated numbers, got {text!r}")
    return values


@dataclass(frozen=True)
class AnalyzeOptions:
    """One run's choices (the command's options); `checked()` refuses impossible ones before any work starts."""

    height_m: float = DEFAULT_HEIGHT_M
    """Ankle-centre-to-shoulder-centre height prior (sets the metric scale)."""
    equal_focal: bool = True
    stride: int = 1
    max_frames: int | None = None
    fps: float | None = None
    """Images per second of an image folder (its frame times; a video's come from the file)."""
    pose_model: str | None = None
    """`thunder`, `lightning` or `auto` (by person size); None: the service's POSEMETRY_POSE_MODEL."""
    threshold: Threshold | str = DEFAULT_THRESHOLD
    """A Threshold, or text such as `6ft` that `checked()` parses."""
    focal_px: float | tuple[float, float] | None = None
    """A known focal length, one value or (fx, fy): then only the ground plane is solved."""
    principal_point_px: tuple[float, float] | None = None
    """A known principal point; None: the image centre, as a prior carried into every sigma."""
    lens: tuple[float, ...] | None = None
    """Known OpenCV lens coefficients (k1, k2, p1, p2[, k3]): keypoints are undistorted before solving."""
    camera_height_m: float | None = None
    """An installer-known camera height above the ground, metres..."""
    camera_height_std_m: float = 0.1
    """... and its tolerance (1-sigma)."""
    distortion: bool = True
    """Estimate lens distortion when the evidence supports it (ignored with a known lens)."""
    sample_cap: int = DEFAULT_SAMPLE_CAP
    write_images: bool = True
    write_video: bool | None = None
    """None: an overlay video for video inputs only."""
    image_format: str = "png"
    unit: str = "m"
    """Unit of the distance labels and of the grid cells (1 m, or 6 ft) in the pictures."""
    model_dir: Path | None = None
    """None: the service's POSEMETRY_MODEL_DIR."""
    detector_input_px: int | None = None
    """Side the person detector sees the frame at; None: the service's POSEMETRY_DETECTOR_INPUT_PX (640)."""
    min_people: int = DEFAULT_MIN_PEOPLE
    """Fewest usable people a calibration is solved from (the service's POSEMETRY_CALIBRATION_MIN_PEOPLE default)."""
    static_after_s: float | None = None
    """Seconds a detection may stand still before its spot is static (service.cameras.static_spots); None: the
    service's POSEMETRY_STATIC_AFTER_S."""
    guided: bool = True
    """Run pose again with the first calibration guiding the detector, and solve again (service/analyze/run.py)."""

    def checked(self) -> AnalyzeOptions:
        """These options with the threshold parsed; AnalyzeError naming the first impossible choice."""
        for name, value, allowed in (
            ("--pose-model", self.pose_model, (*POSE_CHOICES, None)),
            ("--image-format", self.image_format, get_args(ImageFormat)),
            ("--unit", self.unit, get_args(Unit)),
        ):
            if value not in allowed:
                raise AnalyzeError(f"{name} must be one of {', '.join(a for a in allowed if a)}, got {value!r}")
        if not (math.isfinite(self.height_m) and 0.3 <= self.height_m <= 2.5):
            raise AnalyzeError(f"the person height prior must be between 0.3 and 2.5 m, got {self.height_m:g}")
        if self.stride < 1:
            raise AnalyzeError(f"the stride must be at least 1, got {self.stride}")
        if self.max_frames is not None and self.max_frames < 1:
            raise AnalyzeError(f"max frames must be at least 1, got {self.max_frames}")
        focal = () if self.focal_px is None else np.atleast_1d(np.asarray(self.focal_px, dtype=float))
        if len(focal) not in (0, 1, 2) or not all(math.isfinite(f) and 0 < f <= 1e6 for f in focal):
            raise AnalyzeError(
                f"the focal length must be a positive number of pixels (or two: fx, fy), got {self.focal_px}"
            )
        if self.principal_point_px is not None and (
            len(self.principal_point_px) != 2 or not all(math.isfinite(v) for v in self.principal_point_px)
        ):
            raise AnalyzeError(f"the principal point must be two numbers of pixels, got {self.principal_point_px}")
        if self.lens is not None and (len(self.lens) not in (4, 5) or not all(math.isfinite(v) for v in self.lens)):
            raise AnalyzeError(f"the lens needs 4 or 5 OpenCV coefficients (k1, k2, p1, p2[, k3]), got {self.lens}")
        for name, value in (("camera height", self.camera_height_m), ("its tolerance", self.camera_height_std_m)):
            if value is not None and not (math.isfinite(value) and 0 < value <= 1000):
                raise AnalyzeError(f"the {name} must be a positive number of metres, got {value:g}")
        px = self.detector_input_px
        if px is not None and not (32 <= px <= 2048 and px % 32 == 0):
            raise AnalyzeError(f"the detector input size must be a multiple of 32 from 32 to 2048 px, got {px}")
        if self.min_people < 3:
            raise AnalyzeError(f"at least 3 people are needed to calibrate, got --min-people {self.min_people}")
        if self.static_after_s is not None and not (math.isfinite(self.static_after_s) and self.static_after_s > 0):
            raise AnalyzeError(f"--static-after must be a positive number of seconds, got {self.static_after_s:g}")
        if self.sample_cap < 10:
            raise AnalyzeError(f"the calibration sample cap must be at least 10, got {self.sample_cap}")
        threshold = parse_threshold(self.threshold) if isinstance(self.threshold, str) else self.threshold
        return replace(self, threshold=threshold)

    @property
    def threshold_m(self) -> float:
        """The violation threshold in metres (options from `checked()`)."""
        if isinstance(self.threshold, str):
            raise TypeError("unchecked options: call checked() first")
        return self.threshold.metres

    def problem(self, image_size_px: tuple[int, int]) -> CalibrationProblem:
        """What these options tell the geometry about the camera (options from `checked()`)."""
        return CalibrationProblem(
            image_size_px,
            self.height_m,
            equal_focal=self.equal_focal,
            principal_point_px=self.principal_point_px,
            focal_px=self.focal_px,
            lens=None if self.lens is None else OpenCVLens.from_coefficients(self.lens),
            camera_height_m=self.camera_height_m,
            camera_height_std_m=self.camera_height_std_m,
        )

    def as_record(self) -> dict[str, Any]:
        """JSON-ready, for calibration.json: what produced the numbers."""
        record = asdict(self)
        record["threshold"] = str(self.threshold)
        record["threshold_m"] = self.threshold_m
        record["model_dir"] = None if self.model_dir is None else str(self.model_dir)
        return record
