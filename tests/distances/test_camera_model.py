"""What a stored calibration version keeps of its camera model, and what its quality grade does to alerts.

Measuring later must reproduce what the solve knew: a version that lost its lens, ankle height or size-dependent
keypoint noise would place people elsewhere or understate `distance_std_m`. A version graded `unreliable`
measures every pair but raises no violations, on the synchronous endpoint and in the measuring job alike.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import redis
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from bench.simulate import SceneConfig, draw_scene
from service.calibration.camera_model import model_record, quality_record
from service.calibration.repository import add_calibration, current_calibration
from service.domain import CalibrationValues
from service.geometry import CalibrationProblem, OpenCVLens, Quality, calibrate, measure
from service.geometry.uncertainty import CANONICAL_PARAMETERS
from service.queue import RedisDispatcher
from service.store import Frame, ViolationEvent
from tests.support.jobs import run_jobs, simulated_camera, store_frames

LENS = OpenCVLens(k1=-0.15, k2=0.0)


def _lens_scene():
    config = SceneConfig.surveillance(
        n_people=60,
        distortion_k=(LENS.k1, LENS.k2),
        ankle_height_m=0.07,
        noise_px=0.5,
        noise_rel=0.03,
        height_std_m=0.05,
    )
    return draw_scene(config, np.random.default_rng(5))


def _store(app: FastAPI, camera: str, values: CalibrationValues) -> None:
    with app.state.session_factory() as session:
        add_calibration(session, camera, values, make_current=True, forced=True)
        session.commit()


def _people(tops: np.ndarray, bottoms: np.ndarray) -> list[dict[str, object]]:
    return [{"shoulder": t.tolist(), "ankle": b.tolist()} for t, b in zip(tops, bottoms, strict=True)]


def test_a_stored_version_measures_as_its_solve_did(client: TestClient, app: FastAPI) -> None:
    scene = _lens_scene()
    problem = CalibrationProblem((1920, 1080), 1.32, principal_point_px=(scene.cx, scene.cy), lens=LENS)
    cal = calibrate(scene.tops_px, scene.bottoms_px, problem)
    assert cal.uncertainty is not None and cal.uncertainty.noise_per_length > 0 and cal.ankle_height_m > 0
    client.put("/v1/cameras/wide", json={"image_width_px": 1920, "image_height_px": 1080})
    plain = CalibrationValues.from_solution(cal, people_used=60, evidence_count=60)
    _store(app, "wide", replace(plain, camera_model=model_record(cal, problem), quality=quality_record(cal.quality)))

    tops, bottoms = scene.tops_px[:12], scene.bottoms_px[:12]
    result = client.post("/v1/cameras/wide/distances", json={"people": _people(tops, bottoms)}).json()
    expected = measure(cal, tops, bottoms, noise_px=cal.uncertainty.noise_px)
    got = np.array([p["distance_m"] for p in result["pairs"]])
    got_std = np.array([p["distance_std_m"] for p in result["pairs"]])
    i, j = np.triu_indices(12, 1)
    np.testing.assert_allclose(got, expected.distances_m[i, j], rtol=1e-6)
    np.testing.assert_allclose(got_std, expected.distance_std_m[i, j], rtol=1e-6)

    calibration = client.get("/v1/cameras/wide/calibration").json()
    model = calibration["camera_model"]
    assert model["principal_point"] == {
        "source": "given", "cx_px": pytest.approx(scene.cx), "cy_px": pytest.approx(scene.cy),
        "cx_std_px": 0.0, "cy_std_px": 0.0,
    }  # fmt: skip
    assert model["distortion"]["source"] == "given" and model["distortion"]["coefficients"] == list(LENS.coefficients)
    assert model["focal_length"]["source"] == "estimated" and model["focal_length"]["fx_std_px"] > 0
    assert model["inputs"]["principal_point_px"] == [pytest.approx(scene.cx), pytest.approx(scene.cy)]
    with app.state.session_factory() as session:
        stored = current_calibration(session, "wide")
        assert stored is not None and stored.camera_model is not None and stored.covariance is not None
        assert stored.camera_model["covariance_parameters"] == list(CANONICAL_PARAMETERS) == ["fx_px", "fy_px",
            "normal_t1_rad", "normal_t2_rad", "rho_m", "cx_px", "cy_px", "distortion_k"]  # fmt: skip
        assert len(stored.covariance) == 8
    assert calibration["quality"]["grade"] in ("good", "rough", "unreliable")

    # The same numbers without the camera model (a version stored before it existed) lose the lens and the
    # size-dependent noise: other distances, and sigmas that understate.
    _store(app, "wide", plain)
    bare = client.post("/v1/cameras/wide/distances", json={"people": _people(tops, bottoms)}).json()
    bare_std = np.array([p["distance_std_m"] for p in bare["pairs"]])
    assert np.max(np.abs(np.array([p["distance_m"] for p in bare["pairs"]]) - got)) > 0.01
    assert np.median(bare_std / got_std) < 0.9


def _truth_values(scene, grade: str) -> CalibrationValues:
    quality = Quality(grade, 1.5, 12.0, ("only 9 distinct people",), ("more people",), 21)  # type: ignore[arg-type]
    return CalibrationValues(
        status="ok", person_height_m=1.7, people_used=40, inliers=40, evidence_count=40,
        fx_px=scene.fx, fy_px=scene.fy, cx_px=scene.cx, cy_px=scene.cy, normal=tuple(scene.normal.tolist()),
        rho_m=scene.rho, quality=quality_record(quality),
    )  # fmt: skip


def test_an_unreliable_calibration_measures_but_raises_no_violation(client: TestClient, app: FastAPI) -> None:
    scene = draw_scene(SceneConfig.surveillance(n_people=30, noise_px=0.0), np.random.default_rng(3))
    body = {"image_width_px": 1920, "image_height_px": 1080, "person_height_m": 1.7,
            "distance_threshold": {"value": 3, "unit": "m"}}  # fmt: skip
    client.put("/v1/cameras/sim", json=body)
    people = {"people": _people(scene.tops_px, scene.bottoms_px)}
    _store(app, "sim", _truth_values(scene, "rough"))
    trusted = client.post("/v1/cameras/sim/distances", json=people).json()
    assert trusted["violations"] and trusted["calibration_grade"] == "rough" and trusted["alerts_suppressed"] is None
    _store(app, "sim", _truth_values(scene, "unreliable"))
    status = client.get("/v1/cameras/sim/calibration").json()
    assert status["quality"]["grade"] == "unreliable" and status["quality"]["people_needed"] == 21
    result = client.post("/v1/cameras/sim/distances", json=people).json()
    assert result["pairs"] == trusted["pairs"]  # still measured
    assert result["violations"] == [] and result["calibration_grade"] == "unreliable"
    assert f"{len(trusted['violations'])} pairs under the threshold" in result["alerts_suppressed"]


@pytest.mark.parametrize("grade", ["good", "unreliable"])
def test_the_measuring_job_stores_no_violation_event_for_an_unreliable_calibration(
    grade: str, sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    camera = simulated_camera(sessions)
    with sessions() as session, session.begin():
        add_calibration(session, camera.camera_id, _truth_values(camera.scene, grade), make_current=True)
    frames = store_frames(sessions, camera, 3, dispatcher=redis_dispatcher, people=20)
    run_jobs(connection)
    with sessions() as session:
        results = [session.get(Frame, frame).result for frame in frames]
        assert all(result is not None and len(result["pairs"]) == 190 for result in results)
        close = sum(
            p["distance_m"] < 1.8288
            for r in results
            for p in r["pairs"]
            if p["distance_m"] is not None  # type: ignore[index]
        )
        events = session.scalar(select(func.count()).select_from(ViolationEvent))
    assert close > 0
    assert events == (close if grade == "good" else 0)
