"""The geometry tests' helpers: synthetic scenes, the problem fields of the paper's ideal camera, angle errors."""

from __future__ import annotations

import numpy as np

from bench.simulate import Scene, SceneConfig, draw_scene
from service.geometry import Calibration, CalibrationProblem, SolveOptions, calibrate


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


def scene(seed: int, **overrides: object) -> Scene:
    square = bool(overrides.pop("surveillance", False))
    config = SceneConfig.surveillance(**overrides) if square else SceneConfig.paper(**overrides)
    return draw_scene(config, np.random.default_rng(seed))


def solve(s: Scene, options: SolveOptions | None = None, height_m: float = 1.7, **problem: object) -> Calibration:
    """calibrate() on a scene's pixels with its image size; problem holds CalibrationProblem's other fields."""
    return calibrate(s.tops_px, s.bottoms_px, CalibrationProblem(s.image_size, height_m, **problem), options)  # type: ignore[arg-type]


def ideal(s: Scene) -> dict[str, object]:
    """The problem fields that say what the paper's simulator assumes: the principal point at the image centre,
    exactly square pixels, no lens, the crowd's mean height exactly the prior, an unbiased pose model and
    ankles on the ground. With them the model matches the simulator exactly, so sigmas must be calibrated
    and noise-free scenes exact; without them the priors widen every sigma (tests/geometry/test_coverage.py)."""
    return {
        "principal_point_px": (s.image_size[0] / 2.0, s.image_size[1] / 2.0),
        "aspect_std": 0.0,
        "lens_corner_std": 0.0,
        "mean_height_std": 0.0,
        "keypoint_bias_std": 0.0,
        "ankle_height_m": 0.0,
    }


def sightings(
    rng: np.random.Generator, people: int, frames: int, spacing_s: float, *, crowd: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times, tops, bottoms) of `people` sightings in each of `frames` frames `spacing_s` apart, for the linking
    tests: scattered over the image with all sizes and leans, or (`crowd`) standing about in a 100 px square, of
    like size, upright, so that motion and appearance admit many links."""
    n = people * frames
    times = np.repeat(np.arange(frames) * spacing_s, people)
    if crowd:
        bottoms = rng.uniform((800, 600), (900, 700), size=(n, 2))
        return times, bottoms - np.column_stack((np.zeros(n), rng.uniform(120, 140, n))), bottoms
    bottoms = rng.uniform((100, 300), (1800, 1000), size=(n, 2))
    return times, bottoms - np.column_stack((rng.normal(0, 5, n), rng.uniform(60, 200, n))), bottoms


def pairwise_distances(points: np.ndarray) -> np.ndarray:
    """(N, N) Euclidean distances in metres (NaN involving unplaced people): the tests' reference."""
    diff = points[:, None, :] - points[None, :, :]
    return np.sqrt(np.sum(diff * diff, -1))
