"""Grid lines lie on the ground plane, at the cell spacing, and only where the ground is visible."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.render.grid import SIX_FEET_M, grid_segments
from service.render.ground import GroundFrame
from tests.render.scenes import calibration_of, tilted_scene


@pytest.fixture(scope="module")
def frame() -> GroundFrame:
    return GroundFrame.from_calibration(calibration_of(tilted_scene(3)))


def _line_distance(points_a: np.ndarray, points_b: np.ndarray) -> float:
    """Distance between two parallel 3-D lines given by sample points (direction fitted from points_a)."""
    d = points_a[-1] - points_a[0]
    d /= np.linalg.norm(d)
    off = points_b - points_a[0]
    perp = off - (off @ d)[:, None] * d
    return float(np.median(np.linalg.norm(perp, axis=1)))


@pytest.mark.parametrize("cell_m", [1.0, SIX_FEET_M])
@pytest.mark.parametrize("k", [0.0, -0.08])
def test_grid_pixels_back_project_onto_the_plane_at_the_cell_spacing(frame, cell_m, k):
    f = replace(frame, distortion_k=k)
    segments = grid_segments(f, cell_m)
    assert len(segments) > 20
    lines: dict[tuple[int, int], list[np.ndarray]] = {}
    for s in segments:
        x = f.pixels_to_camera(s.pixels)
        assert np.all(np.isfinite(x))
        np.testing.assert_allclose(x @ f.normal + f.rho, 0.0, atol=1e-6)
        uv = f.camera_to_ground(x)
        np.testing.assert_allclose(uv[:, s.axis], s.index * cell_m, atol=1e-6)
        np.testing.assert_allclose(uv, s.ground_m, atol=1e-6)
        lines.setdefault((s.axis, s.index), []).append(x)
    for axis in (0, 1):
        indices = sorted(i for a, i in lines if a == axis)
        pairs = [(i, i + 1) for i in indices if i + 1 in indices][:5]
        assert pairs
        for i, j in pairs:
            a, b = np.vstack(lines[(axis, i)]), np.vstack(lines[(axis, j)])
            assert _line_distance(a, b) == pytest.approx(cell_m, abs=1e-6)
    # Lines of the two families meet at right angles on the ground.
    u_line = np.vstack(lines[(0, 0)])
    v_line = np.vstack(next(v for (a, _), v in lines.items() if a == 1))
    du, dv = u_line[-1] - u_line[0], v_line[-1] - v_line[0]
    assert abs(du @ dv) / (np.linalg.norm(du) * np.linalg.norm(dv)) < 1e-9


def test_grid_stays_in_the_image_and_below_the_horizon(frame):
    segments = grid_segments(frame, 1.0, horizon_margin_px=15.0, max_range_m=np.inf)
    px = np.vstack([s.pixels for s in segments])
    assert np.all(px >= -1e-6) and np.all(px <= np.array([frame.width_px, frame.height_px]) + 1e-6)
    # Without a range limit it reaches exactly the margin below the horizon, and down to the bottom edge.
    assert np.min(frame.below_horizon_px(px)) == pytest.approx(15.0, abs=1e-6)
    assert px[:, 1].max() == pytest.approx(frame.height_px, abs=1e-6)


def test_range_limits_the_grid(frame):
    segments = grid_segments(frame, 1.0, max_range_m=10.0)
    reach = max(float(s.range_m.max()) for s in segments)
    assert 9.0 < reach <= 10.0 * 1.0013


def test_no_grid_when_the_camera_looks_at_the_sky(frame):
    up = replace(frame, normal=np.array([0.0, 0.0, 1.0]))  # ground plane entirely behind the image plane
    assert grid_segments(up, 1.0) == []
    with pytest.raises(ValueError):
        grid_segments(frame, 0.0)
