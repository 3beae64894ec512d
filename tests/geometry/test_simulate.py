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


def test_realistic_scenes_carry_the_mismatches_they_claim() -> None:
    config = SceneConfig.realistic()
    for seed in range(8):
        s = draw_scene(config, np.random.default_rng(seed))
        w, h = s.image_size
        assert np.hypot(s.cx - w / 2, s.cy - h / 2) <= 0.15 * h + 1e-9
        assert abs(s.fy / s.fx - 1.0) <= 0.02 + 1e-12 and s.distortion_k[0] <= 0.0
        # Upright people were placed inside the image; lean, bias and noise may carry a shoulder a little out.
        assert np.all((s.tops_px > -0.05 * h) & (s.tops_px < (w + 0.05 * h, h + 0.05 * h)))
        # Ankles stand above the ground (rho is to the ground), people are seen several times with one height.
        np.testing.assert_allclose(s.points_bottom @ s.normal + s.rho, 0.07 * s.heights / 1.32, atol=1e-9)
        labels, counts = np.unique(s.tracks, return_counts=True)
        assert counts.max() == config.observations_per_person and len(labels) < len(s.tracks)
        for label in labels:
            assert np.ptp(s.heights[s.tracks == label]) == 0.0
        # Bodies lean: the shoulders are not straight above the ankles, by about the configured degrees.
        axis = s.points_top - s.points_bottom
        lean = np.degrees(np.arccos(np.clip(axis @ s.normal / np.linalg.norm(axis, axis=1), -1, 1)))
        assert 0.5 < np.median(lean) < 6.0
