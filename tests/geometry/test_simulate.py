"""The simulator draws what it claims: visible, upright people on the ground of a known camera."""

from __future__ import annotations

import numpy as np
import pytest

from bench.simulate import SceneConfig, draw_scene, project


@pytest.mark.parametrize("config", [SceneConfig.paper(noise_px=0.0), SceneConfig.surveillance(noise_px=0.0)])
def test_scene_consistency(config: SceneConfig) -> None:
    for seed in range(10):
        s = draw_scene(config, np.random.default_rng(seed))
        assert np.linalg.norm(s.normal) == pytest.approx(1.0)
        np.testing.assert_allclose(s.points_bottom @ s.normal + s.rho, 0.0, atol=1e-9)
        np.testing.assert_allclose((s.points_top - s.points_bottom) @ s.normal, s.heights, atol=1e-9)
        for points, pixels in ((s.points_bottom, s.bottoms_px), (s.points_top, s.tops_px)):
            np.testing.assert_allclose(project(points, s.fx, s.fy, s.cx, s.cy), pixels, atol=1e-6)
            assert np.all((pixels >= 0) & (pixels <= s.image_size))
        assert (s.fx == s.fy) == config.square_pixels
        assert config.height_range_m[0] <= s.heights.min() and s.heights.max() <= config.height_range_m[1]


def test_roll_and_pitch_are_within_the_configured_ranges() -> None:
    config = SceneConfig.surveillance()
    for seed in range(20):
        n = draw_scene(config, np.random.default_rng(seed)).normal
        roll = np.degrees(np.arctan2(-n[0], -n[1]))
        pitch = np.degrees(np.arcsin(-n[2]))
        assert abs(roll) <= 5.0 + 1e-9
        assert 10.0 - 1e-9 <= pitch <= 60.0 + 1e-9


def test_outliers_are_marked_and_inside_the_image() -> None:
    s = draw_scene(SceneConfig.paper(n_people=50, outlier_fraction=0.3), np.random.default_rng(0))
    assert s.outliers.sum() == 15
    assert np.all((s.tops_px >= 0) & (s.tops_px <= s.image_size))
