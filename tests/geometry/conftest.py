"""Shared helpers for the geometry tests: exact synthetic scenes and error metrics."""

from __future__ import annotations

import numpy as np
import pytest

from bench.simulate import Scene, SceneConfig, draw_scene
from service.geometry import Calibration, CalibrationProblem, SolveOptions, calibrate


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


def scene(seed: int, **overrides: object) -> Scene:
    square = bool(overrides.pop("surveillance", False))
    config = SceneConfig.surveillance(**overrides) if square else SceneConfig.paper(**overrides)
    return draw_scene(config, np.random.default_rng(seed))


@pytest.fixture
def exact_scene() -> Scene:
    return scene(7, noise_px=0.0, height_std_m=0.0)


def solve(s: Scene, options: SolveOptions | None = None, height_m: float = 1.7, **problem: object) -> Calibration:
    """calibrate() on a scene's pixels with its image size; problem holds CalibrationProblem's other fields."""
    return calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, height_m, **problem), options)  # type: ignore[arg-type]
