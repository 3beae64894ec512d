"""Violation counts per time bucket over HTTP, and the errors of their query."""

from __future__ import annotations

import uuid

from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.calibration.repository import add_calibration
from service.cameras.repository import get_camera
from service.domain import CalibrationValues
from service.frames.repository import get_frame
from tests.support.app import assert_problem, frame_body
from tests.support.measure import process_frame

CLOSE_PAIR = [{"shoulder": [900, 400], "ankle": [900, 700]}, {"shoulder": [960, 400], "ankle": [960, 700]}]


def _calibrated_frames(client: TestClient, app: FastAPI, camera: str, timestamps: list[str]) -> None:
    values = CalibrationValues(
        status="ok", person_height_m=1.32, people_used=30, inliers=30, evidence_count=30,
        fx_px=1000.0, fy_px=1000.0, cx_px=960.0, cy_px=540.0, normal=(0.0, -0.8660254, -0.5), rho_m=4.0,
    )  # fmt: skip
    ids = [client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(CLOSE_PAIR, timestamp=t)).json()["frame_id"]
           for t in timestamps]  # fmt: skip
    with app.state.session_factory() as session:
        cal = add_calibration(session, camera, values, make_current=True)
        cam = get_camera(session, camera)
        for frame_id in ids:
            frame = get_frame(session, camera, uuid.UUID(frame_id))
            process_frame(session, frame, cam, cal)  # type: ignore[arg-type]
        session.commit()


def test_violation_buckets(client: TestClient, app: FastAPI, camera: str) -> None:
    times = ["2026-01-01T12:00:05Z", "2026-01-01T12:00:50Z", "2026-01-01T12:01:10Z", "2026-01-01T13:30:00Z"]
    _calibrated_frames(client, app, camera, times)
    url = f"/v1/cameras/{camera}/violations"
    window = {"since": "2026-01-01T12:00:00Z", "until": "2026-01-01T14:00:00Z"}
    minutes = client.get(url, params=window).json()
    assert [(b["start"][11:16], b["count"]) for b in minutes["buckets"]] == [("12:00", 2), ("12:01", 1), ("13:30", 1)]
    assert minutes["total"] == 4 and minutes["bucket_s"] == 60
    hours = client.get(url, params={**window, "bucket": "hour"}).json()
    assert [(b["start"][11:16], b["count"]) for b in hours["buckets"]] == [("12:00", 3), ("13:00", 1)]
    recent = client.get(url).json()  # default window: the last hour, nothing in it
    assert recent["total"] == 0 and recent["bucket"] == "minute"


def test_violation_query_errors(client: TestClient, camera: str) -> None:
    url = f"/v1/cameras/{camera}/violations"
    assert_problem(client.get(url, params={"since": "2026-01-01T12:00:00"}), 422, "query.since")
    assert_problem(client.get(url, params={"bucket": "day"}), 422, "query.bucket")
    assert_problem(
        client.get(url, params={"since": "2026-01-02T00:00:00Z", "until": "2026-01-01T00:00:00Z"}), 422, "before"
    )
    assert_problem(client.get(url, params={"since": "2000-01-01T00:00:00Z"}), 422, "narrow it")
    assert_problem(client.get("/v1/cameras/ghost/violations"), 404, "no camera")
