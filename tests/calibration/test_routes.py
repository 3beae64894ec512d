"""Calibration status, history, forced re-solve and reset."""

from __future__ import annotations

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.calibration.repository import add_calibration
from service.domain import CalibrationValues
from tests.support.app import MIN_PEOPLE, assert_problem, frame_body, solved, standing
from tests.support.dispatch import RecordingDispatcher


def test_status_goes_uncalibrated_calibrating_calibrated(client: TestClient, camera: str, app: FastAPI) -> None:
    url = f"/v1/cameras/{camera}/calibration"
    status = client.get(url).json()
    assert status["status"] == "uncalibrated" and status["people_needed"] == MIN_PEOPLE
    assert status["evidence_count"] == 0 and status["fx_px"] is None and status["version"] is None
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2)))
    assert client.get(url).json()["people_needed"] == MIN_PEOPLE - 2
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(MIN_PEOPLE)))
    status = client.get(url).json()
    assert status["status"] == "calibrating" and status["people_needed"] == 0
    with app.state.session_factory() as session:
        add_calibration(
            session, camera, CalibrationValues.failure("too few", person_height_m=1.32, people_used=7,
                                                       evidence_count=7), make_current=False
        )  # fmt: skip
        session.commit()
    status = client.get(url).json()
    # The failed solve moved the growth target: 2 x 7 = 14 usable people.
    assert status["status"] == "uncalibrated" and status["people_needed"] == 14 - 7
    assert status["last_failure"] == "too few"
    with app.state.session_factory() as session:
        add_calibration(session, camera, solved(7), make_current=True)
        session.commit()
    status = client.get(url).json()
    assert status["status"] == "calibrated" and status["version"] == 2
    assert status["fx_px"] == 1000.0 and status["normal"] == pytest.approx([0.0, -0.8660254, -0.5])
    assert status["rho_m"] == 4.0 and status["uncertainty"]["fx_std_px"] == 12.0
    assert status["people_used"] == 7 and status["inliers"] == 6 and status["solved_evidence_count"] == 7
    assert status["updated_at"] and status["last_failure"] is None


def test_history_pages_newest_first(client: TestClient, camera: str, app: FastAPI) -> None:
    with app.state.session_factory() as session:
        for fx in (900.0, 1000.0, 1100.0):
            add_calibration(session, camera, solved(10, fx), make_current=True)
        session.commit()
    page = client.get(f"/v1/cameras/{camera}/calibration/history", params={"limit": 2}).json()
    assert [v["version"] for v in page["items"]] == [3, 2] and page["next_before"] == 2
    assert [v["is_current"] for v in page["items"]] == [True, False]
    rest = client.get(f"/v1/cameras/{camera}/calibration/history", params={"limit": 2, "before": 2}).json()
    assert [v["fx_px"] for v in rest["items"]] == [900.0] and rest["next_before"] is None
    assert_problem(client.get("/v1/cameras/none/calibration/history"), 404, "no camera")


def test_force_resolve_and_queue_down(client: TestClient, camera: str, dispatcher: RecordingDispatcher) -> None:
    response = client.post(f"/v1/cameras/{camera}/calibration")
    assert response.status_code == 202 and response.json()["forced"] is True
    assert dispatcher.calibrations == [(camera, True)]
    dispatcher.fail = True
    assert_problem(client.post(f"/v1/cameras/{camera}/calibration"), 503, "queue")
    assert_problem(client.post("/v1/cameras/ghost/calibration"), 404, "no camera")


def test_reset_opens_a_new_epoch_and_can_drop_evidence(
    client: TestClient, camera: str, app: FastAPI, dispatcher: RecordingDispatcher
) -> None:
    fresh = client.get(f"/v1/cameras/{camera}/calibration").json()
    assert (fresh["epoch"], fresh["reason"], fresh["moved_at"]) == (1, None, None)
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(MIN_PEOPLE)))
    with app.state.session_factory() as session:
        add_calibration(session, camera, solved(MIN_PEOPLE), make_current=True)
        session.commit()
    dispatcher.calibrations.clear()
    reset = client.delete(f"/v1/cameras/{camera}/calibration")
    assert reset.status_code == 200
    body = reset.json()
    assert (body["status"], body["reason"], body["epoch"], body["evidence_count"]) == ("uncalibrated", "reset", 2, 0)
    assert body["moved_at"] is None and body["people_needed"] == MIN_PEOPLE
    assert dispatcher.calibrations == []  # the new epoch has no people yet
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(MIN_PEOPLE)))
    assert client.get(f"/v1/cameras/{camera}/calibration").json()["evidence_count"] == MIN_PEOPLE
    dropped = client.delete(f"/v1/cameras/{camera}/calibration", params={"drop_evidence": "true"}).json()
    assert (dropped["status"], dropped["evidence_count"], dropped["epoch"]) == ("uncalibrated", 0, 3)
    history = client.get(f"/v1/cameras/{camera}/calibration/history").json()["items"]
    assert [(item["version"], item["epoch"]) for item in history] == [(1, 1)]
