"""Synchronous distances against the truth of simulated scenes, with the calibration stored via the repository."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from bench.simulate import SceneConfig, draw_scene
from service.calibration.repository import add_calibration
from service.domain import CalibrationValues
from service.geometry import CalibrationProblem, calibrate
from tests.support.app import assert_problem


def _scene(seed: int, noise_px: float):
    config = SceneConfig.surveillance(n_people=40, height_std_m=0.0, noise_px=noise_px, image_size=(1920, 1080))
    return draw_scene(config, np.random.default_rng(seed))


def _camera(client: TestClient, threshold_m: float = 1.8288) -> str:
    body = {"image_width_px": 1920, "image_height_px": 1080, "person_height_m": 1.7,
            "distance_threshold": {"value": threshold_m, "unit": "m"}}  # fmt: skip
    assert client.put("/v1/cameras/sim", json=body).status_code == 201
    return "sim"


def _people(scene, hide_ankles: set[int] = frozenset()) -> list[dict[str, object]]:  # type: ignore[assignment]
    return [
        {"shoulder": scene.tops_px[i].tolist(), "ankle": None if i in hide_ankles else scene.bottoms_px[i].tolist()}
        for i in range(len(scene.tops_px))
    ]


def _truth(scene) -> np.ndarray:
    x = scene.points_bottom
    return np.linalg.norm(x[:, None, :] - x[None, :, :], axis=-1)


def _apart(scene, min_m: float = 0.2) -> list[int]:
    """Indices of the scene's people, leaving out anyone closer than `min_m` to someone before them."""
    x, kept = scene.points_bottom, []
    for i in range(len(x)):
        if all(np.linalg.norm(x[i] - x[k]) >= min_m for k in kept):
            kept.append(i)
    return kept


def test_uncalibrated_camera_is_409(client: TestClient, camera: str) -> None:
    body = {"people": [{"shoulder": [500, 400], "ankle": [500, 700]}]}
    assert_problem(client.post(f"/v1/cameras/{camera}/distances", json=body), 409, "no calibration")
    assert_problem(client.post("/v1/cameras/ghost/distances", json=body), 404, "no camera")
    assert_problem(client.post(f"/v1/cameras/{camera}/distances", json={"people": [], "x": 1}), 422, "body.x")


def test_true_calibration_gives_true_distances(client: TestClient, app: FastAPI) -> None:
    scene = _scene(seed=3, noise_px=0.0)
    camera = _camera(client)
    values = CalibrationValues(
        status="ok", person_height_m=1.7, people_used=40, inliers=40, evidence_count=40,
        fx_px=scene.fx, fy_px=scene.fy, cx_px=scene.cx, cy_px=scene.cy, normal=tuple(scene.normal.tolist()),
        rho_m=scene.rho,
    )  # fmt: skip
    with app.state.session_factory() as session:
        add_calibration(session, camera, values, make_current=True)
        session.commit()
    # The simulation draws places independently: a few people stand closer than two bodies can (5-11 cm here),
    # which the service rightly takes for one body posted twice. Only people 0.2 m apart or more are posted.
    apart = _apart(scene)
    people = [_people(scene, hide_ankles={0, 5})[i] for i in apart]
    people[1]["track_id"] = "walker-1"
    response = client.post(f"/v1/cameras/{camera}/distances", json={"people": people})
    assert response.status_code == 200, response.text
    result = response.json()
    n = len(apart)
    assert n >= 30 and len(result["pairs"]) == n * (n - 1) // 2 and result["calibration_version"] == 1
    truth = _truth(scene)[np.ix_(apart, apart)]
    for pair in result["pairs"]:
        assert pair["distance_m"] == pytest.approx(truth[pair["i"], pair["j"]], rel=1e-6, abs=1e-6)
    assert [p["placed_from"] for p in result["people"][:2]] == ["shoulders", "ankles"]
    assert [p["track_id"] for p in result["people"][:3]] == [None, "walker-1", None]  # echoed as posted
    expected = {(i, j) for i in range(n) for j in range(i + 1, n) if truth[i, j] < 1.8288}
    assert {(v["i"], v["j"]) for v in result["violations"]} == expected
    # Ground coordinates are a rigid map of the ground: they reproduce the distances.
    ground = np.array([p["ground_m"] for p in result["people"]])
    assert np.linalg.norm(ground[0] - ground[1]) == pytest.approx(truth[0, 1], rel=1e-6)


def test_solved_calibration_distances_within_their_uncertainty(client: TestClient, app: FastAPI) -> None:
    evidence = _scene(seed=11, noise_px=1.0)
    camera = _camera(client)
    cal = calibrate(evidence.tops_px, evidence.bottoms_px, CalibrationProblem((1920, 1080), 1.7))
    values = CalibrationValues.from_solution(cal, people_used=40, evidence_count=40)
    with app.state.session_factory() as session:
        add_calibration(session, camera, values, make_current=True)
        session.commit()
    result = client.post(f"/v1/cameras/{camera}/distances", json={"people": _people(evidence)}).json()
    truth = _truth(evidence)
    z = [
        (p["distance_m"] - truth[p["i"], p["j"]]) / p["distance_std_m"] for p in result["pairs"] if p["distance_std_m"]
    ]
    assert len(z) == len(result["pairs"])
    rel = [abs(p["distance_m"] / truth[p["i"], p["j"]] - 1) for p in result["pairs"]]
    assert np.median(rel) < 0.05
    assert np.mean(np.abs(z) < 3) > 0.9


def _calibrate_30_degrees_down(app: FastAPI, camera: str) -> None:
    """A stored calibration: 1000 px, looking 30 degrees down from 4 m, image centre 960, 540."""
    values = CalibrationValues(
        status="ok", person_height_m=1.32, people_used=30, inliers=30, evidence_count=30,
        fx_px=1000.0, fy_px=1000.0, cx_px=960.0, cy_px=540.0, normal=(0.0, -0.8660254, -0.5), rho_m=4.0,
    )  # fmt: skip
    with app.state.session_factory() as session:
        add_calibration(session, camera, values, make_current=True)
        session.commit()


def test_unplaceable_people_and_empty_frames(client: TestClient, app: FastAPI, camera: str) -> None:
    _calibrate_30_degrees_down(app, camera)
    unseen = {"keypoints": [[0.0, 0.0, 0.0]] * 17}  # a detection whose joints all failed
    people = [unseen, {"shoulder": [900, 400], "ankle": [900, 700]}, {"shoulder": [960, 400], "ankle": [960, 700]}]
    result = client.post(f"/v1/cameras/{camera}/distances", json={"people": people}).json()
    assert result["people"][0] == {
        "index": 0,
        "placed_from": None,
        "ground_m": None,
        "point_m": None,
        "static": False,
        "track_id": None,
    }
    assert result["pairs"][0] == {"i": 0, "j": 1, "distance_m": None, "distance_std_m": None}
    assert [(v["i"], v["j"]) for v in result["violations"]] == [(1, 2)]
    empty = client.post(f"/v1/cameras/{camera}/distances", json={"people": []}).json()
    assert empty["people"] == [] and empty["pairs"] == [] and empty["violations"] == []


def test_a_person_posted_twice_is_measured_once(client: TestClient, app: FastAPI, camera: str) -> None:
    """Two people whose shoulders and ankles lie within a few pixels of each other are one body posted twice (a
    client's detector boxing one person twice): the repeat is not placed, so no phantom violation at 0.0x m."""
    _calibrate_30_degrees_down(app, camera)
    person = {"shoulder": [900, 400], "ankle": [900, 700]}
    again = {"shoulder": [902, 401], "ankle": [899, 703]}
    beside = {"shoulder": [960, 400], "ankle": [960, 700]}
    result = client.post(f"/v1/cameras/{camera}/distances", json={"people": [person, again, beside]}).json()
    assert [p["placed_from"] for p in result["people"]] == ["ankles", None, "ankles"]
    assert [(v["i"], v["j"]) for v in result["violations"]] == [(0, 2)]
    alone = client.post(f"/v1/cameras/{camera}/distances", json={"people": [person, beside]}).json()
    assert alone["violations"][0]["distance_m"] == result["violations"][0]["distance_m"]
