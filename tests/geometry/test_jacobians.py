"""The model's exact Jacobians (model.residuals_and_jacobians) against central differences, every parameter."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from service.geometry.model import (
    Layout,
    Linearisation,
    Observations,
    Priors,
    _forward,
    residuals_and_jacobians,
    unpack,
)

MU0_M = 1.7
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _central(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d fun / d x by central differences over x's last axis (steps 1e-6 relative to x), and an estimate of their
    own error: how far those move with the step doubled (rounding, ~eps / step, dominates a column whose
    derivatives are small beside the residuals' other columns)."""
    estimates = []
    for relative in (1e-6, 2e-6):
        out = []
        for i in range(x.shape[-1]):
            step = relative * np.maximum(1.0, np.abs(x[..., i]))
            up, down = x.copy(), x.copy()
            up[..., i] += step
            down[..., i] -= step
            out.append((fun(up) - fun(down)) / (2.0 * np.reshape(step, np.shape(step) + (1,))))
        estimates.append(np.stack(out, -1))
    return estimates[0], np.abs(estimates[0] - estimates[1])


def _full(lin: Linearisation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (n, 4, .) Jacobians the block form stands for: ankle rows weight I on the latent ankle, 0 elsewhere."""
    n = len(lin.r)
    j_theta = np.concatenate((np.zeros((n, 2, lin.j_theta.shape[2])), lin.j_theta), 1)
    j_ankle = np.concatenate((lin.ankle_weight[:, None, None] * np.eye(2), lin.j_ankle), 1)
    j_person = np.concatenate((np.zeros((n, 2, lin.j_person.shape[2])), lin.j_person), 1)
    return j_theta, j_ankle, j_person


def _close(analytic: np.ndarray, numeric: tuple[np.ndarray, np.ndarray], what: str) -> None:
    """Each column within 1e-6 of its own largest entry, beyond the differences' own error (see _central)."""
    values, error = numeric
    scale = np.max(np.abs(values), axis=(0, 1), keepdims=True)
    err = np.abs(analytic - values)
    allowed = 1e-6 * scale + 1e-9 + 4.0 * error
    assert np.all(err <= allowed), f"{what}: max relative error {np.max(err / (scale + 1e-300))}"


@st.composite
def problems(draw: st.DrawFn) -> tuple[Layout, np.ndarray, np.ndarray, Observations, np.ndarray, np.ndarray]:
    focal = draw(st.sampled_from(["equal", "equal+aspect", "free", "fixed"]))
    principal_point = draw(st.booleans())
    lens = draw(st.sampled_from(["estimated", "considered", "absent"]))
    q = draw(st.sampled_from([1, 2]))
    priors = Priors(
        principal_point_n=0.075 if principal_point else None,
        aspect=0.01 if focal == "equal+aspect" else None,
        bias_n=0.004 if draw(st.booleans()) else None,
        distortion_k=None if lens == "absent" else 0.03,
        log_mean_height=0.04 if draw(st.booleans()) else None,
        height_std_rel=0.05,
        lean_rad=0.03 if q == 2 else 0.0,
    )
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    focal_n = rng.uniform(0.7, 3.0)
    fixed = (focal_n, focal_n * rng.uniform(0.98, 1.02)) if focal == "fixed" else None
    layout = Layout.build(focal != "free", fixed, priors, estimate_k=lens == "estimated")
    drawn = {
        "log_f": np.log(focal_n),
        "log_fy": np.log(focal_n) + rng.uniform(-0.02, 0.02),
        "aspect": rng.uniform(-0.02, 0.02),
        "cx": rng.uniform(-0.1, 0.1),
        "cy": rng.uniform(-0.1, 0.1),
        "t1": rng.uniform(-0.1, 0.1),
        "t2": rng.uniform(-0.1, 0.1),
        "log_rho": np.log(rng.uniform(2.5, 20.0)),
        "k": rng.uniform(-0.2, 0.08),
        "bias": rng.uniform(-0.01, 0.01),
        "log_mu": rng.uniform(-0.05, 0.05),
    }
    theta = np.array([drawn[name] for name in layout.names])
    tilt, roll = rng.uniform(0.1, 0.9), rng.uniform(-0.1, 0.1)
    normal0 = np.array([np.sin(roll) * np.cos(tilt), -np.cos(roll) * np.cos(tilt), -np.sin(tilt)])
    n = 60
    ankles = rng.uniform([-1.3, -0.8], [1.3, 0.8], size=(n, 2))
    person = np.column_stack([rng.normal(0.0, 0.06, n), rng.normal(0.0, 0.04, n)][:q])
    # Keep the observations away from every clamp: a step across one would differentiate the kink.
    cam = unpack(layout, theta[None], normal0, MU0_M)
    f = _forward(cam, ankles, cam.mu * (1.0 + person[None, :, 0]), person[None, :, 1] if q == 2 else None)
    keep = (
        (f.denom_raw[0] < -0.05)
        & (f.zt_raw[0] > 0.05 * f.t[0])
        & (f.disc_raw[0, :, 0] > 0.05)
        & (f.length_raw[0, :, 0] > 1e-3)
        & (np.abs(f.spread[0, :, 0]) > 0.2)
    )
    assume(keep.sum() >= 5)
    ankles, person, top = ankles[keep], person[keep], f.top[0][keep]
    m = len(ankles)
    obs = Observations(
        tops_n=top + rng.normal(0.0, 0.004, (m, 2)),
        bottoms_n=ankles + rng.normal(0.0, 0.003, (m, 2)),
        ankle_std_n=rng.uniform(0.002, 0.004, m),
        top_std_n=rng.uniform(0.003, 0.008, m),
        track=np.arange(m),
        tracks=m,
    )
    return layout, theta, normal0, obs, ankles, person


@SETTINGS
@given(problems())
def test_jacobians_equal_central_differences(drawn) -> None:
    layout, theta, normal0, obs, ankles, person = drawn
    lin = residuals_and_jacobians(layout, theta, normal0, MU0_M, obs, ankles, person)
    j_theta, j_ankle, j_person = _full(lin)
    cam = unpack(layout, theta[None], normal0, MU0_M)
    np.testing.assert_allclose(lin.r, obs.residuals(cam, ankles, person)[0], rtol=0.0, atol=1e-12)

    def of_theta(t: np.ndarray) -> np.ndarray:
        return obs.residuals(unpack(layout, t[None], normal0, MU0_M), ankles, person)[0]

    if len(theta):
        _close(j_theta, _central(of_theta, theta), f"theta {layout.names}")
    _close(j_ankle, _central(lambda a: obs.residuals(cam, a, person)[0], ankles), "ankle")
    _close(j_person, _central(lambda h: obs.residuals(cam, ankles, h)[0], person), f"person (q = {person.shape[1]})")


def test_every_parameter_has_a_column_that_moves_the_shoulder() -> None:
    """A parameter the chain rule forgot would read as a zero column and pass a loose comparison."""
    priors = Priors(0.075, 0.01, 0.004, 0.03, 0.04, 0.05, 0.03)
    layout = Layout.build(True, None, priors, estimate_k=True)
    assert set(layout.names) == {"log_f", "aspect", "cx", "cy", "t1", "t2", "log_rho", "k", "bias", "log_mu"}
    theta = np.array([np.log(1.4), 0.01, 0.02, -0.03, 0.05, -0.04, np.log(6.0), -0.05, 0.005, 0.02])
    normal0 = np.array([0.0, -np.cos(0.5), -np.sin(0.5)])
    rng = np.random.default_rng(0)
    ankles = rng.uniform([-1.0, 0.0], [1.0, 0.7], (20, 2))
    person = np.column_stack((rng.normal(0.0, 0.05, 20), rng.normal(0.0, 0.03, 20)))
    obs = Observations(ankles, ankles, np.full(20, 0.003), np.full(20, 0.005), np.arange(20), 20)
    j_theta, j_ankle, j_person = _full(residuals_and_jacobians(layout, theta, normal0, MU0_M, obs, ankles, person))
    assert np.all(np.abs(j_theta[:, 2:]).max(axis=(0, 1)) > 1e-3)
    assert np.all(j_theta[:, :2] == 0.0) and np.all(j_person[:, :2] == 0.0)
    assert np.all(np.abs(j_person[:, 2:]).max(axis=(0, 1)) > 1e-3)
    np.testing.assert_array_equal(j_ankle[:, :2], np.eye(2) / 0.003 * np.ones((20, 1, 1)))


def test_beyond_the_lens_horizon_the_derivatives_are_what_central_differences_see() -> None:
    """Shoulders beyond the lens's horizon (the distortion's discriminant clamped at 0): its derivative is 0, as
    a step inside the clamp sees. (A ray above the horizon puts the shoulder on the ankle, a segment ~1e-9 long
    whose differences are rounding, so that clamp is not compared.)"""
    priors = Priors(0.075, 0.01, 0.004, 0.03, 0.04, 0.05, 0.03)
    layout = Layout.build(True, None, priors, estimate_k=True)
    theta = np.array([np.log(1.2), 0.01, 0.02, -0.03, 0.02, -0.01, np.log(5.0), 0.3, 0.005, 0.02])
    normal0 = np.array([0.0, -np.cos(0.5), -np.sin(0.5)])
    rng = np.random.default_rng(1)
    # Undistorted radii never pass the horizon (max r / (1 + k r^2) = 1 / (2 sqrt k)); shoulders outside
    # ankles at the widest radius do. The view is widened to find them.
    ankles = rng.uniform([-2.0, -1.0], [2.0, 2.0], (400, 2))
    person = np.column_stack((rng.normal(0.0, 0.05, 400), rng.normal(0.0, 0.03, 400)))
    cam = unpack(layout, theta[None], normal0, MU0_M)
    f = _forward(cam, ankles, cam.mu * (1.0 + person[None, :, 0]), person[None, :, 1])
    keep = (f.denom_raw[0] < -0.05) & (np.abs(f.disc_raw[0, :, 0]) > 0.05)
    keep &= (f.zt_raw[0] > 0.05 * f.t[0]) & (f.length_raw[0, :, 0] > 1e-3)
    assert (keep & (f.disc_raw[0, :, 0] < 0.0)).sum() >= 10 and (keep & (f.disc_raw[0, :, 0] > 0.0)).sum() >= 10
    ankles, person, m = ankles[keep], person[keep], int(keep.sum())
    obs = Observations(ankles, ankles, np.full(m, 0.003), np.full(m, 0.005), np.arange(m), m)
    j_theta, j_ankle, j_person = _full(residuals_and_jacobians(layout, theta, normal0, MU0_M, obs, ankles, person))

    def of_theta(t: np.ndarray) -> np.ndarray:
        return obs.residuals(unpack(layout, t[None], normal0, MU0_M), ankles, person)[0]

    _close(j_theta, _central(of_theta, theta), "theta")
    _close(j_ankle, _central(lambda a: obs.residuals(cam, a, person)[0], ankles), "ankle")
    _close(j_person, _central(lambda h: obs.residuals(cam, ankles, h)[0], person), "person")
