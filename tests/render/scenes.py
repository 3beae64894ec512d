"""Synthetic calibrated scenes for the render tests and the sample pictures (no I/O)."""

from __future__ import annotations

import numpy as np

from bench.simulate import Scene, SceneConfig, draw_scene
from service.domain import PersonIn
from service.frames.schemas import FrameResult
from service.frames.service import compute_frame_result
from service.geometry.calibration import Calibration
from service.store.models import CalibrationVersion


def tilted_scene(
    seed: int = 3, *, size: tuple[int, int] = (1280, 720), n_people: int = 8, **overrides: object
) -> Scene:
    """A surveillance-like camera pitched down 15-20 degrees with some roll: the horizon crosses the image."""
    config = SceneConfig.surveillance(
        image_size=size,
        n_people=n_people,
        noise_px=0.0,
        height_std_m=0.0,
        pitch_deg=(15.0, 20.0),
        roll_deg=(4.0, 6.0),
        vfov_deg=(55.0, 60.0),
        camera_height_m=(4.0, 5.0),
        max_range_m=12.0,
        **overrides,
    )
    return draw_scene(config, np.random.default_rng(seed))


def calibration_of(scene: Scene, height_m: float = 1.7) -> Calibration:
    """The scene's true camera as a Calibration (per-person arrays empty)."""
    return Calibration(
        fx=scene.fx,
        fy=scene.fy,
        cx=scene.cx,
        cy=scene.cy,
        normal=np.asarray(scene.normal, dtype=float),
        rho=scene.rho,
        image_size=(float(scene.image_size[0]), float(scene.image_size[1])),
        height_m=height_m,
        points_bottom=np.zeros((0, 3)),
        points_top=np.zeros((0, 3)),
        heights=np.zeros(0),
        inliers=np.zeros(0, dtype=bool),
    )


def version_of(cal: Calibration) -> CalibrationVersion:
    """A transient stored calibration row with the same camera (no session needed)."""
    return CalibrationVersion(
        version=1,
        status="ok",
        fx_px=cal.fx,
        fy_px=cal.fy,
        cx_px=cal.cx,
        cy_px=cal.cy,
        normal_x=float(cal.normal[0]),
        normal_y=float(cal.normal[1]),
        normal_z=float(cal.normal[2]),
        rho_m=cal.rho,
        covariance=None,
        noise_px=0.0,
        distortion_k=cal.distortion_k,
        person_height_m=cal.height_m,
    )


def people_of(scene: Scene, hide_ankles: tuple[int, ...] = ()) -> list[PersonIn]:
    """The scene's people as posted centres; those in `hide_ankles` are shoulder-only."""
    return [
        PersonIn(
            shoulder_px=(float(t[0]), float(t[1])),
            ankle_px=None if i in hide_ankles else (float(b[0]), float(b[1])),
        )
        for i, (t, b) in enumerate(zip(scene.tops_px, scene.bottoms_px, strict=True))
    ]


def result_of(scene: Scene, people: list[PersonIn], threshold_m: float) -> FrameResult:
    """The FrameResult the service would store for these people with the scene's true camera."""
    cal = calibration_of(scene)
    return compute_frame_result(
        people, version_of(cal), image_size_px=scene.image_size, distance_threshold_m=threshold_m
    ).result
