"""/metrics after real traffic, request ids from header to database, and the JSON access log (in-process API)."""

from __future__ import annotations

import io
import uuid

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.calibration.repository import add_calibration
from service.domain import CalibrationValues
from service.observability.request_id import REQUEST_ID_MAX_LENGTH
from service.store import Frame
from tests.support.app import assert_problem, frame_body, standing
from tests.support.logs import json_lines, json_log
from tests.support.scrape import Scrape

KEYPOINTS_ROUTE = "/v1/cameras/{camera_id}/keypoints"
DURATION_COUNT = "posemetry_http_request_duration_seconds_count"
__all__ = ["json_log"]  # a fixture


def scrape(client: TestClient) -> Scrape:
    response = client.get("/metrics")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/plain")
    return Scrape(response.text)


def requests_seen(client: TestClient, route: str, method: str, status_class: str) -> float:
    return scrape(client).value(DURATION_COUNT, route=route, method=method, status_class=status_class) or 0.0


# --------------------------------------------------------------------------------------------------- metrics


def test_latency_histogram_is_labelled_by_route_template(client: TestClient, camera: str) -> None:
    before = requests_seen(client, KEYPOINTS_ROUTE, "POST", "2xx")
    refused_before = requests_seen(client, KEYPOINTS_ROUTE, "POST", "4xx")
    client.put("/v1/cameras/cam-2", json={"image_width_px": 1920, "image_height_px": 1080})
    for camera_id in (camera, camera, "cam-2"):
        assert client.post(f"/v1/cameras/{camera_id}/keypoints", json=frame_body(standing(2))).status_code == 202
    # Refused by the body guard before routing, still counted under its route.
    oversize = client.post(f"/v1/cameras/{camera}/keypoints", content=b"[" * 300_000)
    assert oversize.status_code == 413
    client.get("/no/such/route")
    after = scrape(client)
    assert after.value(DURATION_COUNT, route=KEYPOINTS_ROUTE, method="POST", status_class="2xx") == before + 3
    assert after.value(DURATION_COUNT, route=KEYPOINTS_ROUTE, method="POST", status_class="4xx") == refused_before + 1
    assert (after.value(DURATION_COUNT, route="unmatched", method="GET", status_class="4xx") or 0) >= 1
    # Raw paths never become label values: the series count stays bounded by the routes.
    routes = {labels["route"] for labels in after.labelsets(DURATION_COUNT)}
    assert not any("cam-" in route or "/no/such" in route for route in routes), routes
    assert "/v1/cameras/{camera_id}" in routes
    buckets = [
        s
        for s in after.samples
        if s.name == "posemetry_http_request_duration_seconds_bucket" and s.labels["route"] == KEYPOINTS_ROUTE
    ]
    assert buckets and all(s.value >= 0 for s in buckets)
    total = after.value(
        "posemetry_http_request_duration_seconds_sum", route=KEYPOINTS_ROUTE, method="POST", status_class="2xx"
    )
    assert total is not None and 0 < total < 60
    # The scrape itself is the one request in progress.
    assert after.value("posemetry_http_requests_in_progress") == 1


def test_frames_ingested_count_new_frames_by_source(client: TestClient, camera: str) -> None:
    name = "posemetry_frames_ingested_total"
    before = scrape(client)
    for _ in range(2):  # a retry of the same client frame id is not a new frame
        client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2), frame_id="once"))
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2)))
    after = scrape(client)
    assert after.value(name, source="keypoints") == before.value(name, source="keypoints") + 2
    assert after.value(name, source="image") == before.value(name, source="image")


def test_calibration_state_and_evidence_per_camera(client: TestClient, camera: str, app: FastAPI) -> None:
    client.put("/v1/cameras/cam-2", json={"image_width_px": 1920, "image_height_px": 1080})
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(7)))
    client.post("/v1/cameras/cam-2/keypoints", json=frame_body([{"shoulder": [900, 300], "ankle": None}]))
    values = CalibrationValues(
        status="ok", person_height_m=1.32, people_used=7, inliers=7, evidence_count=7, fx_px=1000.0, fy_px=1000.0,
        cx_px=960.0, cy_px=540.0, normal=(0.0, -0.8660254, -0.5), rho_m=4.0,
    )  # fmt: skip
    with app.state.session_factory() as session:
        add_calibration(session, camera, CalibrationValues.failure("few", person_height_m=1.32,
                                   people_used=7, evidence_count=7), make_current=False)  # fmt: skip
        record = add_calibration(session, camera, values, make_current=True)
        solved_at = record.created_at.timestamp()
        session.commit()
    metrics = scrape(client)
    assert metrics.value("posemetry_camera_calibrated", camera=camera) == 1
    assert metrics.value("posemetry_camera_calibration_version", camera=camera) == 2
    assert metrics.value("posemetry_camera_calibration_timestamp_seconds", camera=camera) == pytest.approx(solved_at)
    assert metrics.value("posemetry_camera_usable_evidence", camera=camera) == 7
    assert metrics.value("posemetry_camera_calibrated", camera="cam-2") == 0
    assert metrics.value("posemetry_camera_calibration_version", camera="cam-2") == 0
    assert metrics.value("posemetry_camera_calibration_timestamp_seconds", camera="cam-2") is None
    assert metrics.value("posemetry_camera_usable_evidence", camera="cam-2") == 0  # no ankle: not evidence
    assert metrics.value("posemetry_camera_calibration_epoch", camera=camera) == 1
    assert metrics.value("posemetry_camera_moves_total", camera=camera) == 0
    assert metrics.value("posemetry_metrics_source_up", source="database") == 1
    assert metrics.value("posemetry_metrics_source_up", source="redis") is None  # no queue in this app
    client.delete("/v1/cameras/cam-2")
    assert scrape(client).value("posemetry_camera_calibrated", camera="cam-2") is None  # gone with the camera


def test_openmetrics_is_served_when_asked_for(client: TestClient) -> None:
    response = client.get("/metrics", headers={"accept": "application/openmetrics-text; version=1.0.0"})
    assert response.headers["content-type"].startswith("application/openmetrics-text")
    assert response.text.rstrip().endswith("# EOF")


# --------------------------------------------------------------------------------------------------- request ids


def test_request_id_round_trip_from_header_to_stored_frame(client: TestClient, camera: str, app: FastAPI) -> None:
    sent = "client-trace:42.a_b-C"
    response = client.post(
        f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2)), headers={"X-Request-ID": sent}
    )
    assert response.status_code == 202 and response.headers["x-request-id"] == sent
    with app.state.read_session_factory() as session:
        assert session.get(Frame, uuid.UUID(response.json()["frame_id"])).request_id == sent
    problem = client.get(f"/v1/cameras/{camera}/frames/{uuid.uuid4()}", headers={"X-Request-ID": "lookup-1"})
    body = assert_problem(problem, 404, "no frame")
    assert body["request_id"] == problem.headers["x-request-id"] == "lookup-1"


def test_a_generated_request_id_is_returned_and_stored(client: TestClient, camera: str, app: FastAPI) -> None:
    first = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2)))
    second = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2)))
    ids = [first.headers["x-request-id"], second.headers["x-request-id"]]
    assert ids[0] != ids[1] and all(len(i) == 32 and int(i, 16) >= 0 for i in ids)
    with app.state.read_session_factory() as session:
        assert session.get(Frame, uuid.UUID(first.json()["frame_id"])).request_id == ids[0]


@pytest.mark.parametrize(
    "malformed",
    ["a" * (REQUEST_ID_MAX_LENGTH + 1), "has space", 'quote"d', "semi;colon", "-leading-dash", "new\\nline", "x/y"],
)
def test_a_malformed_request_id_is_replaced_not_echoed(
    client: TestClient, camera: str, malformed: str, json_log: io.StringIO
) -> None:
    response = client.put(f"/v1/cameras/{camera}", json={"image_width_px": 0, "image_height_px": 1},
                          headers={"X-Request-ID": malformed})  # fmt: skip
    body = assert_problem(response, 422)
    replacement = response.headers["x-request-id"]
    assert replacement != malformed and len(replacement) == 32
    assert body["request_id"] == replacement
    assert malformed not in response.text and malformed not in json_log.getvalue()


def test_the_longest_well_formed_request_id_is_kept(client: TestClient) -> None:
    longest = "r" * REQUEST_ID_MAX_LENGTH
    assert client.get("/healthz", headers={"X-Request-ID": longest}).headers["x-request-id"] == longest


def test_an_unexpected_error_carries_the_request_id(app: FastAPI, json_log: io.StringIO) -> None:
    def broken() -> None:
        raise RuntimeError("bug in a handler")

    app.add_api_route("/broken", broken)
    with TestClient(app, raise_server_exceptions=False) as client:
        response = client.get("/broken", headers={"X-Request-ID": "oops-1"})
    body = assert_problem(response, 500)
    assert body["request_id"] == response.headers["x-request-id"] == "oops-1"
    lines = json_lines(json_log)
    error = next(line for line in lines if line["message"].startswith("unhandled error"))
    assert error["request_id"] == "oops-1" and "RuntimeError: bug in a handler" in error["exc_info"]
    access = next(line for line in lines if line["logger"] == "posemetry.access")
    assert access["status"] == 500 and access["request_id"] == "oops-1" and access["route"] == "/broken"


# --------------------------------------------------------------------------------------------------- logs


def test_one_json_access_line_per_request(client: TestClient, camera: str, json_log: io.StringIO) -> None:
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2)), headers={"X-Request-ID": "line-1"})
    client.get("/v1/cameras/missing", headers={"X-Request-ID": "line-2"})
    client.get("/healthz")  # probes log at DEBUG, below the level
    lines = json_lines(json_log)  # every line is one JSON object
    access = [line for line in lines if line["logger"] == "posemetry.access"]
    assert [line["request_id"] for line in access] == ["line-1", "line-2"]
    posted, missing = access
    assert posted["method"] == "POST" and posted["route"] == KEYPOINTS_ROUTE and posted["status"] == 202
    assert posted["path"] == f"/v1/cameras/{camera}/keypoints" and posted["camera_id"] == camera
    assert 0 < posted["duration_ms"] < 60_000 and posted["level"] == "INFO" and posted["time"].endswith("+00:00")
    assert missing["status"] == 404 and missing["camera_id"] == "missing"
    # Lines written while serving a request carry its id even when the code did not pass it.
    assert all("request_id" in line for line in lines if line["logger"].startswith("service."))
