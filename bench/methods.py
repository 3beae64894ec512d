"""The benchmark's methods: named calibrate() configurations, the settings they run on, and one calibration of a scene.

A method is a named set of CalibrationProblem and SolveOptions fields (METHODS): add a variant there and name it
in an experiment's method list to benchmark it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from bench.simulate import Scene, SceneConfig
from service.geometry import CalibrationError, CalibrationProblem, SolveOptions, calibrate

from .metrics import TrialResult, evaluate, true_outliers
from .paper_literal import calibrate_paper_literal

# Named CalibrationProblem and SolveOptions fields (split by name). Experiments add the image size, the
# height prior, equal_focal, the paper's assumptions and the seed; a method's own entries take precedence.
# "solver": "paper-literal" runs the paper's printed solver instead of calibrate().
METHODS: dict[str, dict[str, Any]] = {
    "linear": {"robust": False, "refine": False, "uncertainty": False},
    "robust": {"robust": True, "refine": False, "uncertainty": False},
    "default": {},
    "no-lens": {"distortion": False},
    # The paper's solver as printed (corrected): pixel coordinates, unweighted, people from their depths.
    "as-printed": {"solver": "paper-literal"},
}


@dataclass(frozen=True)
class Setting:
    """One column of a table: what scenes to draw and how to call calibrate() on them."""

    label: str
    config: SceneConfig
    equal_focal: bool = False
    # Calibrate on the scene's true inliers only: what perfect outlier rejection would achieve.
    drop_outliers: bool = False
    # CalibrationProblem fields this setting's scenes justify (e.g. exact heights on noise-free scenes).
    problem: Mapping[str, Any] = field(default_factory=dict)


def without_outliers(scene: Scene) -> Scene:
    keep = ~true_outliers(scene)
    return replace(
        scene,
        points_bottom=scene.points_bottom[keep],
        points_top=scene.points_top[keep],
        heights=scene.heights[keep],
        tops_px=scene.tops_px[keep],
        bottoms_px=scene.bottoms_px[keep],
        outliers=np.zeros(int(keep.sum()), dtype=bool),
    )


def paper_assumptions(image_size: tuple[float, float]) -> dict[str, Any]:
    """What the paper's protocol assumes (and its simulator draws): the principal point at the image centre,
    no lens, square or known-aspect pixels, the crowd's mean height known, an unbiased pose model, ankles on
    the ground. The paper's tables are run under them so that they compare solvers, not camera models
    (bench.coverage measures the camera model on real cameras' mismatches)."""
    return {
        "principal_point_px": (image_size[0] / 2.0, image_size[1] / 2.0),
        "aspect_std": 0.0,
        "lens_corner_std": 0.0,
        "mean_height_std": 0.0,
        "keypoint_bias_std": 0.0,
        "ankle_height_m": 0.0,
    }


def problem_and_options(
    image_size: tuple[float, float], height_m: float, equal_focal: bool, method: Mapping[str, Any], seed: int
) -> tuple[CalibrationProblem, SolveOptions]:
    """A method's entries split into the problem's and the options' fields (under the paper's assumptions,
    which a method's own entries override); TypeError for any other name."""
    problem_fields = {f.name for f in fields(CalibrationProblem)}
    problem: dict[str, Any] = {
        "image_size_px": image_size,
        "height_m": height_m,
        "equal_focal": equal_focal,
        **paper_assumptions(image_size),
    }
    options: dict[str, Any] = {"seed": seed}
    for key, value in method.items():
        (problem if key in problem_fields else options)[key] = value
    return CalibrationProblem(**problem), SolveOptions(**options)


def run_method(scene: Scene, setting: Setting, method: Mapping[str, Any], seed: int) -> TrialResult:
    height_m = setting.config.height_mean_m
    try:
        if method.get("solver") == "paper-literal":
            cal = calibrate_paper_literal(
                scene.tops_px, scene.bottoms_px, scene.image_size, height_m, setting.equal_focal
            )
        else:
            merged = {**setting.problem, **method}
            problem, options = problem_and_options(scene.image_size, height_m, setting.equal_focal, merged, seed)
            cal = calibrate(scene.tops_px, scene.bottoms_px, problem, options)
    except CalibrationError as exc:
        return TrialResult.failure(str(exc))
    except Exception as exc:  # a worker must not die: one bug would lose every other trial's result
        return TrialResult.failure(f"{type(exc).__name__}: {exc}", unexpected=True)
    return evaluate(scene, cal)
