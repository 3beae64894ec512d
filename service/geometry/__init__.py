"""Camera auto-calibration and metric reconstruction from human pose (pure numpy/scipy, no I/O).

Implements Fei et al., "Single View Physical Distance Estimation using Human
Pose" (ICCV 2021), with the printed formulas corrected and verified on exact
synthetic scenes. Conventions: pixel origin top-left; camera frame x right,
y down, z forward; ground plane normal . X + rho = 0 with the normal pointing up.

    cal = calibrate(tops_px, bottoms_px, CalibrationProblem((W, H), height_m=1.32))
    m = measure(cal, tops_px, bottoms_px)   # positions, distances and their 1-sigma
    ms = measure_many(cal, tops_px, bottoms_px, people_per_frame)   # many frames in one pass

Layout (PoseLib-style): camera (the camera model: principal point, focal lengths,
lens, rays, projection), minimal (minimal solvers), linear (the batch solver),
ransac (one generic loop) and consensus (its use on people), refine (the
maximum-likelihood fit), uncertainty and measure (what the covariance says about
any derived quantity), problem (what a calibration is asked), calibrate (the
pipeline).
"""

from .calibrate import calibrate
from .calibration import Calibration, Quality, Uncertainty
from .camera import OpenCVLens
from .errors import CalibrationError
from .measure import Measurement, Measurements, measure, measure_many
from .priors import DEFAULT_HEIGHT_M, DEFAULT_HEIGHT_STD_M
from .problem import CalibrationProblem, SolveOptions
from .quality import assess

__all__ = [
    "DEFAULT_HEIGHT_M",
    "DEFAULT_HEIGHT_STD_M",
    "Calibration",
    "CalibrationError",
    "CalibrationProblem",
    "Measurement",
    "Measurements",
    "OpenCVLens",
    "Quality",
    "SolveOptions",
    "Uncertainty",
    "assess",
    "calibrate",
    "measure",
    "measure_many",
]
