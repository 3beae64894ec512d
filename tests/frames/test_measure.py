"""A frame's result as the worker stores it: FrameResult's shape, strict JSON, and the truth of the scene."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from service.domain import PersonIn
from service.frames.keypoints import PARTIAL_REASON, SEATED_REASON, STATIC_REASON
from service.frames.measure import SEATED_HEIGHT_FRACTION, measure_people
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


def _shoulders_at(scene_cal: object, ground_m: np.ndarray, height_m: float) -> tuple[float, float]:
    """Pixel of a point `height_m` straight above a ground point (N points up)."""
    point = ground_m + height_m * scene_cal.normal  # type: ignore[attr-defined]
    pixel = scene_cal.camera.project(point[None])[0]  # type: ignore[attr-defined]
    return float(pixel[0]), float(pixel[1])


def test_people_who_are_not_evidence_are_placed_measured_and_flagged_with_a_wider_sigma() -> None:
    """Seated and partly seen people count: placed from what was trusted, with the sigma their posture implies."""
    scene = tilted_scene(n_people=6)
    cal = calibration_of(scene)
    ground = scene.points_bottom
    standing = PersonIn(
        shoulder_px=tuple(scene.tops_px[0]),
        ankle_px=tuple(scene.bottoms_px[0]),  # type: ignore[arg-type]
    )
    # Person 1 sits: shoulders 0.78 of the standing height above their true ground point, ankles under a table.
    seated_shoulders = _shoulders_at(cal, ground[1], SEATED_HEIGHT_FRACTION * cal.height_m)
    seated = PersonIn(shoulder_px=seated_shoulders, ankle_px=None, unusable_reason=SEATED_REASON, posture="seated")
    read_as_standing = PersonIn(shoulder_px=seated_shoulders, ankle_px=None)
    result = measure_people([standing, seated, read_as_standing], cal, distance_threshold_m=THRESHOLD_M).result
    assert [p.placed_from for p in result.people] == ["ankles", "shoulders", "shoulders"]
    true_m = float(np.linalg.norm(ground[0] - ground[1]))
    by_pair = {(p.i, p.j): p for p in result.pairs}
    assert abs(by_pair[0, 1].distance_m - true_m) < 1e-6  # the seated prior puts them where they sit
    assert abs(by_pair[0, 2].distance_m - true_m) > 0.1  # the standing prior would not

    # Lower body unseen: standing or seated, so the standing prior with a sigma that covers both.
    partial = PersonIn(
        shoulder_px=tuple(scene.tops_px[1]),  # type: ignore[arg-type]
        ankle_px=None,
        unusable_reason=PARTIAL_REASON,
        posture="partial",
    )
    upright = PersonIn(shoulder_px=tuple(scene.tops_px[1]), ankle_px=None)  # type: ignore[arg-type]
    result = measure_people([standing, partial, upright], cal, distance_threshold_m=THRESHOLD_M).result
    by_pair = {(p.i, p.j): p for p in result.pairs}
    assert by_pair[0, 1].distance_m == pytest.approx(by_pair[0, 2].distance_m)
    assert by_pair[0, 1].distance_std_m > 3 * by_pair[0, 2].distance_std_m > 0


def test_a_partly_seen_person_close_to_another_is_a_violation() -> None:
    scene = tilted_scene(n_people=6)
    cal = calibration_of(scene)
    ground = scene.points_bottom[0]
    beside = ground + 0.8 * np.cross(cal.normal, [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(cal.normal, [0, 0, 1]))
    standing = PersonIn(shoulder_px=_shoulders_at(cal, ground, cal.height_m), ankle_px=_shoulders_at(cal, ground, 0))
    partial = PersonIn(
        shoulder_px=_shoulders_at(cal, beside, cal.height_m),
        ankle_px=None,
        unusable_reason=PARTIAL_REASON,
        posture="partial",
    )
    result = measure_people([standing, partial], cal, distance_threshold_m=THRESHOLD_M).result
    assert result.pairs[0].distance_m == pytest.approx(0.8, abs=1e-6)
    assert [(v.i, v.j) for v in result.violations] == [(0, 1)]


def test_a_static_person_is_measured_but_in_no_violation() -> None:
    scene = tilted_scene(n_people=6)
    cal = calibration_of(scene)
    ground = scene.points_bottom[0]
    beside = ground + 0.5 * np.cross(cal.normal, [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(cal.normal, [0, 0, 1]))
    people = [
        PersonIn(shoulder_px=_shoulders_at(cal, point, cal.height_m), ankle_px=_shoulders_at(cal, point, 0))
        for point in (ground, beside)
    ]
    result = measure_people(people, cal, distance_threshold_m=THRESHOLD_M).result
    assert [(v.i, v.j) for v in result.violations] == [(0, 1)]
    people[1] = replace(people[1], unusable_reason=STATIC_REASON, static=True)
    result = measure_people(people, cal, distance_threshold_m=THRESHOLD_M).result
    assert result.pairs[0].distance_m == pytest.approx(0.5, abs=1e-6)
    assert result.violations == [] and [p.static for p in result.people] == [False, True]
