"""The benchmark's error metrics on hand-made examples whose answers are known exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench.geometry import summarise
from bench.methods import Setting, run_method, without_outliers
from bench.metrics import TrialResult, angle_deg, distance_errors, evaluate, point_errors_pct, relative_error_pct
from bench.simulate import Scene, SceneConfig, draw_scene
from service.geometry import Calibration


def exact_calibration(scene: Scene, **changes: object) -> Calibration:
    """A calibration that reproduces the scene's truth, with some fields overridden."""
    n = len(scene.points_bottom)
    fields: dict[str, object] = {
        "fx": scene.fx,
        "fy": scene.fy,
        "cx": scene.cx,
        "cy": scene.cy,
        "normal": scene.normal.copy(),
        "rho": scene.rho,
        "image_size": scene.image_size,
        "height_m": 1.7,
        "points_bottom": scene.points_bottom.copy(),
        "points_top": scene.points_top.copy(),
        "heights": scene.heights.copy(),
        "inliers": np.ones(n, dtype=bool),
    }
    fields.update(changes)
    return Calibration(**fields)  # type: ignore[arg-type]


@pytest.fixture
def scene() -> Scene:
    config = SceneConfig.paper(n_people=10, noise_px=0.0, height_std_m=0.0, outlier_fraction=0.3)
    return draw_scene(config, np.random.default_rng(3))


def test_relative_error_of_a_known_ten_percent_focal_error() -> None:
    assert relative_error_pct(1100.0, 1000.0) == pytest.approx(10.0, abs=1e-12)
    assert relative_error_pct(900.0, 1000.0) == pytest.approx(10.0, abs=1e-12)
    assert relative_error_pct(1000.0, 1000.0) == 0.0


def test_angle_of_orthogonal_opposite_and_equal_normals() -> None:
    assert angle_deg([0.0, -1.0, 0.0], [1.0, 0.0, 0.0]) == pytest.approx(90.0, abs=1e-12)
    assert angle_deg([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]) == pytest.approx(180.0, abs=1e-12)
    assert angle_deg([0.0, 0.0, 2.0], [0.0, 0.0, 1.0]) == 0.0


def test_angle_keeps_precision_where_arccos_does_not() -> None:
    tiny = 1e-9  # radians
    a, b = np.array([0.0, -1.0, 0.0]), np.array([np.sin(tiny), -np.cos(tiny), 0.0])
    assert float(np.arccos(np.clip(a @ b, -1, 1))) == 0.0  # the naive formula reports an exact answer
    assert angle_deg(a, b) == pytest.approx(math.degrees(tiny), rel=1e-6)


@given(st.floats(0.0, 3.0), st.floats(0.1, 10.0))
def test_angle_is_scale_invariant_and_matches_the_construction(angle_rad: float, scale: float) -> None:
    a = np.array([1.0, 0.0, 0.0])
    b = scale * np.array([np.cos(angle_rad), np.sin(angle_rad), 0.0])
    assert angle_deg(a, b) == pytest.approx(math.degrees(angle_rad), abs=1e-9)


def test_point_and_distance_errors_of_a_scaled_reconstruction() -> None:
    truth = np.array([[0.0, 1.5, 5.0], [3.0, 1.5, 5.0], [3.0, 1.5, 9.0]])  # pair distances 3, 4, 5 m
    estimate = 1.1 * truth
    np.testing.assert_allclose(point_errors_pct(estimate, truth), 10.0)
    pct, metres = distance_errors(estimate, truth)
    np.testing.assert_allclose(pct, [10.0, 10.0, 10.0])
    np.testing.assert_allclose(np.sort(metres), [0.3, 0.4, 0.5])


def test_exact_calibration_has_zero_error_and_outliers_are_left_out(scene: Scene) -> None:
    assert scene.outliers.sum() == 3
    # Outliers' estimated positions are wherever the calibration put them; they must not count.
    points_bottom = scene.points_bottom.copy()
    points_bottom[scene.outliers] += 7.0
    result = evaluate(scene, exact_calibration(scene, points_bottom=points_bottom))
    assert not result.failed
    for key in ("fx_pct", "fy_pct", "normal_deg", "rho_pct", "points_pct", "dist_pct", "dist_m"):
        assert result.metrics[key] == pytest.approx(0.0, abs=1e-9), key
    assert result.metrics["inliers_placed_pct"] == 100.0
    assert result.metrics["outliers_placed_pct"] == 100.0


def test_known_camera_errors_are_reported(scene: Scene) -> None:
    tilt = np.radians(2.0)
    across = np.cross(scene.normal, [1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    tilted = np.cos(tilt) * scene.normal + np.sin(tilt) * across
    cal = exact_calibration(scene, fx=1.1 * scene.fx, fy=0.95 * scene.fy, rho=1.2 * scene.rho, normal=tilted)
    result = evaluate(scene, cal)
    assert result.metrics["fx_pct"] == pytest.approx(10.0)
    assert result.metrics["fy_pct"] == pytest.approx(5.0)
    assert result.metrics["rho_pct"] == pytest.approx(20.0)
    assert result.metrics["normal_deg"] == pytest.approx(2.0)


def test_rejected_people_are_not_scored_and_lower_the_kept_share(scene: Scene) -> None:
    inliers = np.ones(len(scene.points_bottom), dtype=bool)
    first_true_inlier = int(np.flatnonzero(~scene.outliers)[0])
    inliers[first_true_inlier] = False
    points_bottom = scene.points_bottom.copy()
    points_bottom[first_true_inlier] = np.nan
    result = evaluate(scene, exact_calibration(scene, inliers=inliers, points_bottom=points_bottom))
    assert result.metrics["points_pct"] == pytest.approx(0.0, abs=1e-9)
    assert result.metrics["inliers_placed_pct"] == pytest.approx(100.0 * 6 / 7)


def test_non_finite_camera_is_a_failure(scene: Scene) -> None:
    result = evaluate(scene, exact_calibration(scene, fx=float("nan")))
    assert result.failed
    assert not result.unexpected


def test_calibration_error_is_a_failure_and_other_exceptions_are_flagged(scene: Scene) -> None:
    setting = Setting("x", SceneConfig.paper())
    refused = run_method(scene, setting, {"focal_px": -1.0}, seed=0)
    assert refused.failed and not refused.unexpected
    broken = run_method(scene, setting, {"no_such_argument": 1}, seed=0)
    assert broken.failed and broken.unexpected and "TypeError" in broken.error


def test_summary_averages_successful_trials_only() -> None:
    ok = [
        TrialResult(
            {
                "fx_pct": v,
                "fy_pct": v,
                "normal_deg": v,
                "rho_pct": v,
                "points_pct": v,
                "dist_pct": v,
                "dist_m": v,
                "inliers_placed_pct": 100.0,
                "outliers_placed_pct": math.nan,
            }
        )
        for v in (1.0, 2.0, 6.0)
    ]
    summary = summarise([*ok, TrialResult.failure("refused")])
    assert summary.fail_pct == 25.0
    assert summary.mean["fx_pct"] == pytest.approx(3.0)
    assert summary.median["fx_pct"] == pytest.approx(2.0)
    assert summary.max["fx_pct"] == pytest.approx(6.0)
    assert math.isnan(summary.mean["outliers_placed_pct"])
    assert summary.first_error == "refused"


def test_without_outliers_keeps_only_true_inliers(scene: Scene) -> None:
    clean = without_outliers(scene)
    assert len(clean.tops_px) == 7
    np.testing.assert_array_equal(clean.points_bottom, scene.points_bottom[~scene.outliers])
    assert not clean.outliers.any()
