"""Camera auto-calibration and metric reconstruction from human pose (pure numpy/scipy, no I/O).

Implements Fei et al., "Single View Physical Distance Estimation using Human
Pose" (ICCV 2021), with the printed formulas corrected and verified on exact
synthetic scenes. Conventions: pixel origin top-left; camera frame x right,
y down, z forward; ground plane normal . X + rho = 0 with the normal pointing up.

    cal = calibrate(tops_px, bottoms_px, image_size=(W, H), height=1.7)
    m = measure(cal, tops_px, bottoms_px)   # positions, distances and their 1-sigma
"""

from .calibrate import calibrate
from .calibration import Calibration, Uncertainty
from .errors import CalibrationError
from .measure import Measurement, measure
from .priors import DEFAULT_HEIGHT_M, DEFAULT_HEIGHT_STD_M

__all__ = [
    "DEFAULT_HEIGHT_M",
    "DEFAULT_HEIGHT_STD_M",
    "Calibration",
    "CalibrationError",
    "Measurement",
    "Uncertainty",
    "calibrate",
    "measure",
]
