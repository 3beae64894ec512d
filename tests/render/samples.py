"""Sample pictures for a person to look at: `python -m tests.render.samples [OUT_DIR]` (default /tmp/render_samples).

Synthetic scenes from the simulator (overlay on grey, top-down, heat map) and, when the shared Oxford Town
Centre frame and its published calibration are present, the ground grid on that real frame.
"""

from __future__ import annotations

import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import cv2
import numpy as np

from service.render.grid import SIX_FEET_M
from service.render.heatmap import ViolationPoint, render_heatmap
from service.render.overlay import marks_from_result, render_overlay
from service.render.png import encode_png
from service.render.topdown import fit_view, render_topdown
from tests.render.oxford import oxford_calibration, oxford_people, undistort_frame
from tests.render.scenes import calibration_of, people_of, result_of, tilted_scene
from tests.support.shared import TOWN_CENTRE

THRESHOLD_M = SIX_FEET_M
SHARED = TOWN_CENTRE


Spot = tuple[tuple[float, float], float]


def synthetic_violations(
    seed: int = 0, spots: tuple[Spot, Spot, Spot] = (((2.0, 8.0), 0.6), ((-3.0, 5.0), 0.5), ((0.0, 7.0), 4.0))
) -> list[ViolationPoint]:
    """A morning of violations: 300 around a busy spot, 80 around a second one, 60 scattered (centre, spread in m)."""
    rng = np.random.default_rng(seed)
    t0 = datetime(2026, 1, 5, 8, 0, tzinfo=UTC)
    out = []
    for n, (centre, spread) in zip((300, 80, 60), spots, strict=True):
        pts = rng.normal(centre, spread, (n, 2))
        minutes = rng.gamma(4.0, 10.0, n)
        out += [
            ViolationPoint(t0 + timedelta(minutes=float(m)), (float(p[0]), float(p[1])))
            for p, m in zip(pts, minutes, strict=True)
        ]
    return out


def main(out_dir: str = "/tmp/render_samples") -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, size in (("1080p", (1920, 1080)), ("640x480", (640, 480)), ("portrait", (720, 1280))):
        scene = tilted_scene(3 if name != "portrait" else 5, size=size)
        cal = calibration_of(scene)
        people = people_of(scene, hide_ankles=(1,))
        result = result_of(scene, people, THRESHOLD_M)
        marks = marks_from_result(result, people, cal)
        grey = np.full((size[1], size[0], 3), 110, np.uint8)
        (out / f"overlay_{name}.png").write_bytes(
            encode_png(render_overlay(grey, cal, marks, result.pairs, THRESHOLD_M, grid_cell_m=1.0))
        )
        if name == "1080p":
            six = render_overlay(grey, cal, marks, result.pairs, THRESHOLD_M, grid_cell_m=SIX_FEET_M, unit="ft")
            (out / "overlay_1080p_6ft.png").write_bytes(encode_png(six))
            top = render_topdown(marks, result.pairs, THRESHOLD_M, size_px=(800, 800), calibration=cal)
            (out / "topdown.png").write_bytes(encode_png(top))
    violations = synthetic_violations()
    (out / "heatmap.png").write_bytes(encode_png(render_heatmap(violations, bucket="minute", size_px=(800, 600))))
    view = fit_view([v.ground_m for v in violations], (800, 600))
    hourly = render_heatmap(violations, bucket=600, view=view)
    (out / "heatmap_10min.png").write_bytes(encode_png(hourly))
    frame_path = SHARED / "frames" / "clip_000000.jpg"
    calib_path = SHARED / "TownCentre-calibration-ci.txt"
    if frame_path.exists() and calib_path.exists():
        frame = undistort_frame(cv2.imread(str(frame_path)), calib_path)
        cal = oxford_calibration(calib_path, (frame.shape[1], frame.shape[0]))
        marks, pairs = oxford_people(SHARED / "TownCentre-groundtruth.top", cal, frame_number=0)
        fig1 = render_overlay(frame, cal, marks, pairs, THRESHOLD_M, grid_cell_m=SIX_FEET_M, unit="ft")
        (out / "oxford_fig1_6ft.png").write_bytes(encode_png(fig1))
        top = render_topdown(marks, pairs, THRESHOLD_M, size_px=(800, 800), calibration=cal, unit="ft")
        (out / "oxford_topdown.png").write_bytes(encode_png(top))
        (out / "oxford_grid_6ft.png").write_bytes(
            encode_png(render_overlay(frame, cal, [], [], THRESHOLD_M, grid_cell_m=SIX_FEET_M))
        )
        street = synthetic_violations(1, spots=(((0.0, 16.0), 1.0), ((-5.0, 24.0), 0.8), ((2.0, 20.0), 5.0)))
        (out / "oxford_heatmap.png").write_bytes(
            encode_png(render_heatmap(street, background=frame, calibration=cal, bucket=600))
        )
    print("\n".join(sorted(str(p) for p in out.glob("*.png"))))


if __name__ == "__main__":
    main(*sys.argv[1:])
