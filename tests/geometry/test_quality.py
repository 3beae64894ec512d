"""What a calibration is worth: the grade follows the predicted error, and thin or narrow evidence says why."""

from __future__ import annotations

import numpy as np

from bench.simulate import SceneConfig, draw_scene
from service.geometry import CalibrationProblem, calibrate
from service.geometry.quality import GOOD_2SIGMA_M, MIN_INDIVIDUALS, assess


def test_a_well_sampled_camera_with_known_intrinsics_is_good() -> None:
    s = draw_scene(SceneConfig.surveillance(n_people=150, noise_px=1.0), np.random.default_rng(2))
    cal = calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, 1.7, principal_point_px=(s.cx, s.cy)))
    q = cal.quality
    assert q is not None and q == assess(cal)
    assert q.grade == "good" and q.distance_2sigma_m <= GOOD_2SIGMA_M and not q.reasons
    assert 0 < q.typical_range_m < 35 and q.people_needed == 0


def test_thin_evidence_is_unreliable_and_says_what_would_help() -> None:
    s = draw_scene(SceneConfig.surveillance(n_people=8, noise_px=1.5), np.random.default_rng(5))
    cal = calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, 1.7))
    q = cal.quality
    assert q is not None and q.grade == "unreliable"
    assert any(f"at least {MIN_INDIVIDUALS}" in reason for reason in q.reasons)
    assert q.people_needed >= 22 and q.advice[0].startswith("more people")


def test_the_predicted_error_grows_without_intrinsics_and_with_noise() -> None:
    s = draw_scene(SceneConfig.surveillance(n_people=80, noise_px=1.0), np.random.default_rng(7))
    known = calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, 1.7, principal_point_px=(s.cx, s.cy)))
    free = calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, 1.7))
    assert known.quality is not None and free.quality is not None
    assert free.quality.distance_2sigma_m > known.quality.distance_2sigma_m
    noisy = draw_scene(SceneConfig.surveillance(n_people=80, noise_px=6.0), np.random.default_rng(7))
    worse = calibrate(noisy.tops_px, noisy.bottoms_px, CalibrationProblem(noisy.image_size, 1.7))
    assert worse.quality is not None and worse.quality.distance_2sigma_m > free.quality.distance_2sigma_m


def test_people_at_one_distance_are_too_narrow() -> None:
    s = draw_scene(SceneConfig.surveillance(n_people=200, noise_px=1.0), np.random.default_rng(9))
    ranges = np.linalg.norm(s.points_bottom + s.rho * s.normal, axis=1)
    band = np.abs(ranges - np.median(ranges)) < 0.1 * np.median(ranges)
    cal = calibrate(s.tops_px[band], s.bottoms_px[band], CalibrationProblem(s.image_size, 1.7))
    q = cal.quality
    assert q is not None and q.grade == "unreliable"
    assert any("one distance" in reason for reason in q.reasons)
