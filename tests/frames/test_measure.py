"""A frame's result as the worker stores it: FrameResult's shape, strict JSON, and the truth of the scene."""

from __future__ import annotations

import json

import numpy as np

from service.domain import PersonIn
from service.frames.schemas import FrameResult
from service.frames.service import compute_frame_result
from tests.render.scenes import calibration_of, people_of, tilted_scene, version_of

THRESHOLD_M = 1.8288


def test_the_stored_document_is_a_frame_result_and_measures_the_scene() -> None:
    scene = tilted_scene(n_people=12)
    people = [*people_of(scene, hide_ankles=(2,)), PersonIn(shoulder_px=None, ankle_px=None)]  # one unplaceable
    computation = compute_frame_result(
        people, version_of(calibration_of(scene)), image_size_px=scene.image_size, distance_threshold_m=THRESHOLD_M
    )
    stored = json.loads(computation.result_json())
    result = FrameResult.model_validate(stored)
    # What is stored is exactly the model's own serialisation: readers of frames.result see one shape.
    assert json.loads(result.model_dump_json()) == stored
    assert len(result.people) == 13 and len(result.pairs) == 13 * 12 // 2
    assert [p.placed_from for p in result.people[:4]] == ["ankles", "ankles", "shoulders", "ankles"]
    assert result.people[12].placed_from is None and result.people[12].ground_m is None
    truth = scene.points_bottom
    for pair in result.pairs:
        if pair.j == 12:
            assert pair.distance_m is None and pair.distance_std_m is None
            continue
        true_m = float(np.linalg.norm(truth[pair.i] - truth[pair.j]))
        # Noise-free scene, true camera: exact, except for the shoulder-placed person (height prior 1.7 m vs theirs).
        tolerance = 0.05 if 2 in (pair.i, pair.j) else 1e-6
        assert abs(pair.distance_m - true_m) <= tolerance * max(true_m, 1.0), (pair, true_m)
    expected = {(p.i, p.j) for p in result.pairs if p.distance_m is not None and p.distance_m < THRESHOLD_M}
    assert {(v.i, v.j) for v in result.violations} == expected
    assert {(v.person_i, v.person_j) for v in computation.violations} == expected
    assert computation.result == result


def test_no_people_is_an_empty_result() -> None:
    scene = tilted_scene()
    computation = compute_frame_result(
        [], version_of(calibration_of(scene)), image_size_px=scene.image_size, distance_threshold_m=THRESHOLD_M
    )
    assert json.loads(computation.result_json()) == {
        "calibration_version": 1,
        "distance_threshold_m": THRESHOLD_M,
        "people": [],
        "pairs": [],
        "violations": [],
        "calibration_grade": None,
        "alerts_suppressed": None,
    }
