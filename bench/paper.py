"""Published simulation results of Fei et al. (ICCV 2021), Tables 1-3, for side-by-side comparison.

Copied from /work/shared/docs/fei2021-single-view-distance.tex. Each value is a
mean over the paper's 5,000 Monte Carlo trials (successful ones, for the error
rows); columns follow the order of the settings in the matching table.
"""

from __future__ import annotations

from typing import Final

# Metric keys match bench.geometry.METRIC_KEYS plus "fail_pct".
PaperRows = dict[str, dict[str, tuple[float, ...]]]

PAPER_TRIALS: Final = 5000

TABLE1_NOISE_PX: Final = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0)
TABLE2_HEIGHT_STD_M: Final = (0.05, 0.1, 0.15, 0.2, 0.25)
TABLE3_PEOPLE: Final = (5, 10, 20, 50, 100)

TABLE1: Final[PaperRows] = {
    "Ours": {
        "fx_pct": (0.65, 1.66, 3.11, 6.04, 11.93, 28.03),
        "fy_pct": (0.73, 1.67, 2.99, 5.51, 10.52, 24.97),
        "normal_deg": (0.09, 0.18, 0.45, 0.90, 1.84, 4.60),
        "rho_pct": (0.24, 0.50, 1.23, 2.38, 4.86, 12.41),
        "points_pct": (0.67, 1.36, 2.88, 5.33, 10.71, 24.70),
        "fail_pct": (0.08, 0.32, 1.06, 1.52, 4.10, 13.72),
    },
    "Baseline": {
        "fx_pct": (1.20, 2.00, 4.58, 8.43, 14.90, 32.69),
        "fy_pct": (1.27, 1.95, 4.33, 7.71, 13.97, 27.44),
        "normal_deg": (0.20, 0.33, 0.83, 1.71, 3.72, 9.70),
        "rho_pct": (0.51, 0.88, 2.24, 5.15, 13.18, 39.08),
        "points_pct": (2.16, 3.27, 6.16, 10.56, 17.31, 31.57),
        "fail_pct": (0.32, 0.40, 1.76, 3.84, 8.24, 27.28),
    },
}

TABLE2: Final[PaperRows] = {
    "Ours": {
        "fx_pct": (4.66, 8.18, 11.60, 13.10, 13.87),
        "fy_pct": (5.20, 7.52, 11.17, 11.74, 12.25),
        "normal_deg": (0.79, 1.35, 1.87, 2.20, 2.40),
        "rho_pct": (2.06, 3.52, 4.88, 5.77, 6.45),
        "points_pct": (4.91, 8.03, 10.52, 12.36, 13.81),
        "fail_pct": (1.44, 2.30, 3.48, 4.46, 5.36),
    },
    "Baseline": {
        "fx_pct": (7.39, 11.77, 14.14, 15.73, 16.14),
        "fy_pct": (6.80, 10.39, 12.39, 13.97, 14.78),
        "normal_deg": (1.41, 2.42, 3.02, 3.64, 3.77),
        "rho_pct": (3.71, 6.27, 7.83, 9.19, 9.78),
        "points_pct": (8.56, 14.38, 15.80, 20.41, 20.37),
        "fail_pct": (2.74, 4.66, 6.12, 6.80, 7.68),
    },
}

TABLE3: Final[PaperRows] = {
    "Ours": {
        "fx_pct": (21.03, 14.15, 8.17, 6.36, 5.27),
        "fy_pct": (20.38, 11.47, 8.24, 5.44, 4.78),
        "normal_deg": (3.87, 2.21, 1.39, 0.92, 0.76),
        "rho_pct": (10.24, 5.79, 3.87, 2.66, 2.19),
        "points_pct": (16.31, 12.73, 10.39, 9.50, 9.31),
        "fail_pct": (9.88, 4.70, 2.28, 1.84, 1.52),
    },
    "Baseline": {
        "fx_pct": (21.53, 15.62, 12.40, 11.59, 12.39),
        "fy_pct": (17.53, 14.11, 13.05, 12.79, 12.55),
        "normal_deg": (4.87, 3.62, 2.93, 2.70, 2.61),
        "rho_pct": (13.71, 9.33, 7.60, 6.77, 6.19),
        "points_pct": (20.55, 19.94, 18.00, 18.57, 17.91),
        "fail_pct": (13.78, 7.20, 5.1, 4.2, 4.0),
    },
}
