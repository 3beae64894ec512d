"""Camera auto-calibration and metric reconstruction from human pose (pure numpy/scipy, no I/O).

Implements Fei et al., "Single View Physical Distance Estimation using Human
Pose" (ICCV 2021), with the printed formulas corrected and verified on exact
synthetic scenes. Conventions: pixel origin top-left; camera frame x right,
y down, z forward; ground plane normal . X + rho = 0 with the normal pointing up.
"""

from .calibrate import DEFAULT_HEIGHT_M, calibrate
from .calibration import Calibration, Uncertainty
from .errors import CalibrationError

__all__ = ["DEFAULT_HEIGHT_M", "Calibration", "CalibrationError", "Uncertainty", "calibrate"]
