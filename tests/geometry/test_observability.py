"""What people determine about a camera, checked on exact synthetic scenes (the fact issue 16 builds on).

Derivation. Camera K (square pixels, focal f, principal point p), ground N . X + rho = 0 (unit N, up), a
person of height h with ankle X_B on the ground and shoulder X_T = X_B + h N. With v = K N (the vertical
vanishing point) and l = K^-T N (the horizon), N . X_B = -rho gives the ankle's depth from its pixel b:
X_B = -rho K^-1 b / (l . b), so

    t ~ K X_T = K X_B + h K N ~ b - (h / rho) (l . b) v,   i.e.   t ~ (I - (h / rho) v l^T) b   (with l . v = 1).

Every person's shoulder pixel is a planar homology of their ankle pixel with vertex v, axis l and ratio
h / rho: people's pixels depend on the camera only through v (2 numbers), l (2) and h / rho (1). Five
numbers; the camera has six once the principal point is free (f, cx, cy, the normal's two angles, rho).

Which camera gives the same five? For square pixels l ~ omega v with omega = K^-T K^-1, which reads
l ~ (v - p, f^2 - (v - p) . p) for v = (v, 1): the horizon is perpendicular to v - p, so p lies on the line
through v perpendicular to the horizon (the parallel component of p is determined). Along that line, with
d_v = |v - p| and d_l the distance from p to the horizon, (v - p) . (x - p) = -f^2 on the horizon gives
f^2 = d_v d_l. Moving p by s towards v keeps v, l and h / rho with d_v' = d_v - s, d_l' = d_l + s,
f' = sqrt(d_v' d_l'), N' ~ K'^-1 v and rho' = rho: the perpendicular component of p trades against f and the
tilt with no change in any pixel, hence in any residual. And scaling rho and every h together leaves h / rho,
so a known camera height adds nothing to f or N that the person height prior did not already fix: it only
sets the scale.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bench.coverage import evaluate
from bench.simulate import SceneConfig, draw_scene
from service.geometry import CalibrationProblem, SolveOptions, calibrate
from service.geometry.camera import project
from tests.support.geometry import angle_deg, ideal


def _scene():  # type: ignore[no-untyped-def]
    config = SceneConfig.surveillance(noise_px=0.0, height_std_m=0.0, n_people=40, roll_deg=(3.0, 8.0))
    return draw_scene(config, np.random.default_rng(11))


def _vanishing_point_and_horizon(f: float, p: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k = np.array([[f, 0.0, p[0]], [0.0, f, p[1]], [0.0, 0.0, 1.0]])
    v = k @ normal
    horizon = np.linalg.inv(k).T @ normal
    return v[:2] / v[2], horizon / np.linalg.norm(horizon[:2])


def _equivalent_camera(
    f: float, p: np.ndarray, normal: np.ndarray, shift_px: float
) -> tuple[float, np.ndarray, np.ndarray]:
    """The camera with the principal point moved by shift_px towards v along the perpendicular to the horizon."""
    v, _ = _vanishing_point_and_horizon(f, p, normal)
    d_v = float(np.linalg.norm(v - p))
    towards = (v - p) / d_v
    d_l = f * f / d_v
    p2 = p + shift_px * towards
    f2 = float(np.sqrt((d_v - shift_px) * (d_l + shift_px)))
    n2 = np.array([*((v - p2) / f2), 1.0]) * np.sign(normal[2])
    return f2, p2, n2 / np.linalg.norm(n2)


def _pixels(
    f: float, p: np.ndarray, normal: np.ndarray, rho: float, bottoms_px: np.ndarray, height_m: float
) -> np.ndarray:
    """Shoulder pixels of people of height_m whose ankles are seen at bottoms_px, for one camera."""
    rays = np.column_stack(((bottoms_px - p) / f, np.ones(len(bottoms_px))))
    feet = rays * (-rho / (rays @ normal))[:, None]
    tops = feet + height_m * normal
    return f * tops[:, :2] / tops[:, 2:] + p


@pytest.mark.parametrize("shift_px", [-150.0, -40.0, 60.0, 200.0])
def test_the_principal_point_across_the_horizon_trades_against_f_and_tilt_with_no_pixel_changed(
    shift_px: float,
) -> None:
    s = _scene()
    p = np.array([s.cx, s.cy])
    f2, p2, n2 = _equivalent_camera(s.fx, p, s.normal, shift_px)
    v1, l1 = _vanishing_point_and_horizon(s.fx, p, s.normal)
    v2, l2 = _vanishing_point_and_horizon(f2, p2, n2)
    np.testing.assert_allclose(v2, v1, atol=1e-6)
    np.testing.assert_allclose(l2 * np.sign(l2[2]), l1 * np.sign(l1[2]), atol=1e-12)
    # Every person's shoulders land on the same pixel under both cameras: no residual can tell them apart...
    tops2 = _pixels(f2, p2, n2, s.rho, s.bottoms_px, s.heights[0])
    np.testing.assert_allclose(tops2, s.tops_px, atol=1e-6)
    # ... though they differ in f and in the tilt.
    assert abs(f2 / s.fx - 1.0) > 0.005 and angle_deg(n2, s.normal) > 0.2


def test_calibrate_fits_both_principal_points_on_the_perpendicular_exactly_and_a_parallel_shift_not() -> None:
    s = _scene()
    p = np.array([s.cx, s.cy])
    f2, p2, n2 = _equivalent_camera(s.fx, p, s.normal, 120.0)
    exact = {**ideal(s), "height_std_m": 1e-6}
    options = SolveOptions(uncertainty=True)
    moved = calibrate(
        s.tops_px,
        s.bottoms_px,
        CalibrationProblem(s.image_size, 1.7, **{**exact, "principal_point_px": tuple(p2)}),
        options,
    )
    assert moved.fx == pytest.approx(f2, rel=1e-6) and angle_deg(moved.normal, n2) < 1e-5
    assert moved.rho == pytest.approx(s.rho, rel=1e-6) and moved.reprojection_rms_px < 1e-4
    # Along the horizon instead, the principal point leaves the perpendicular through v: the people no longer fit.
    _, horizon = _vanishing_point_and_horizon(s.fx, p, s.normal)
    along = np.array([horizon[1], -horizon[0]])
    off = tuple(p + 120.0 * along)
    wrong = calibrate(
        s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, 1.7, **{**exact, "principal_point_px": off}), options
    )
    assert wrong.reprojection_rms_px > 1000 * moved.reprojection_rms_px


def test_the_evidence_fixes_the_parallel_component_and_leaves_the_perpendicular_to_the_prior() -> None:
    """With the principal point free, its posterior is narrow along the horizon and the prior's width across it."""
    s = draw_scene(SceneConfig.surveillance(noise_px=0.5, n_people=200, roll_deg=(0.0, 1.0)), np.random.default_rng(3))
    cal = calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, 1.7))
    unc = cal.uncertainty
    assert unc is not None
    prior_px = CalibrationProblem(s.image_size).principal_point_std * s.image_size[1]
    # A nearly level roll: the horizon is nearly horizontal, so cx is the parallel and cy the perpendicular part.
    assert unc.cy_px == pytest.approx(prior_px, rel=0.05)
    assert unc.cx_px < 0.5 * prior_px


def test_a_known_camera_height_sets_the_scale_and_nothing_else() -> None:
    s = _scene()
    base = {**ideal(s), "height_std_m": 0.05, "mean_height_std": 0.04}

    def solve(height_m: float, **extra: object):  # type: ignore[no-untyped-def]
        return calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, height_m, **base, **extra))

    known = {"camera_height_m": s.rho, "camera_height_std_m": 0.01}
    # The height prior right: the camera height confirms the scale and tells nothing about f or the ground.
    without, with_height = solve(1.7), solve(1.7, **known)
    assert with_height.fx == pytest.approx(without.fx, rel=1e-6)
    assert angle_deg(with_height.normal, without.normal) < 1e-5
    assert with_height.rho == pytest.approx(without.rho, rel=1e-6) == pytest.approx(s.rho, rel=1e-6)
    assert with_height.uncertainty is not None and without.uncertainty is not None
    assert with_height.uncertainty.rho_m < 0.5 * without.uncertainty.rho_m
    # f's sigma barely moves (a known mean height then weighs the implied heights' average a little).
    assert with_height.uncertainty.fx_px == pytest.approx(without.uncertainty.fx_px, rel=0.15)
    # The prior 6 % short (people of 1.7 m solved as 1.6 m): the scale follows the prior without the camera
    # height and the camera height with it; f moves only by what the compromise between the two priors
    # spreads over the individuals' heights.
    short, corrected = solve(1.6), solve(1.6, **known)
    assert short.rho == pytest.approx(s.rho * 1.6 / 1.7, rel=1e-3)
    assert corrected.rho == pytest.approx(s.rho, rel=2e-3)
    assert corrected.fx == pytest.approx(short.fx, rel=0.01)


@pytest.mark.parametrize("above", [True, False])
def test_a_cropped_streams_principal_point_lies_inside_the_reported_two_sigma(above: bool) -> None:
    """Issue 16's held-out layouts sit up to 17 % of the image height off centre (streams cropped or shifted in
    the camera). Across the horizon the people cannot see such an offset, so the tilt and f it costs must lie
    inside the 2 sigma the principal point's prior carries. On this exact scene a prior of 6 % of the height puts
    the normal outside it (Mahalanobis 2-sigma), 7.5 % and 9 % inside; the simulator's tail, where noise and the
    other mismatches add up, is what chose 9 % (docs/benchmarks/camera-model.md)."""
    config = SceneConfig.surveillance(noise_px=0.0, height_std_m=0.0, n_people=200, roll_deg=(0.0, 1.0))
    s = draw_scene(config, np.random.default_rng(3))
    cy = s.cy + (-0.17 if above else 0.17) * s.image_size[1]
    cropped = replace(
        s,
        cy=cy,
        tops_px=project(s.points_top, s.fx, s.fy, s.cx, cy, s.distortion_k),
        bottoms_px=project(s.points_bottom, s.fx, s.fy, s.cx, cy, s.distortion_k),
    )
    exact_but_the_principal_point = {k: v for k, v in ideal(s).items() if k != "principal_point_px"}
    cal = calibrate(
        cropped.tops_px, cropped.bottoms_px, CalibrationProblem(s.image_size, 1.7, **exact_but_the_principal_point)
    )
    row = evaluate(cropped, cal)
    assert row["normal_deg"] > 2.0 and row["f_pct"] > 1.0  # the offset costs the tilt and f: not vacuous
    assert row["f_covered"] and row["normal_covered"] and row["rho_covered"], row
