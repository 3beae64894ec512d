"""Violation counts per time bucket over HTTP, and the errors of their query."""

from __future__ import annotations

import uuid
from datetime import UTC, datetime, timedelta

import cv2
import numpy as np
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


def test_frames_posted_now_as_readme_does_fill_the_default_windows(
    client: TestClient, app: FastAPI, camera: str
) -> None:
    """README's examples post frames taken now (`date -u`) and read the counts and the heat map without a window: the
    defaults (the last hour of minutes, the last day of hours) must show them. Frames of another day must not be in
    them, and the picture then says the window is empty."""
    now = datetime.now(UTC).replace(microsecond=0)
    _calibrated_frames(
        client, app, camera, [(now - timedelta(minutes=2)).isoformat(), (now - timedelta(days=3)).isoformat()]
    )
    assert client.get(f"/v1/cameras/{camera}/violations").json()["total"] == 1
    assert client.get(f"/v1/cameras/{camera}/violations?bucket=hour").json()["total"] == 1
    url = f"/v1/cameras/{camera}/violations/heatmap.png"
    shown = decode(client.get(url, params={"bucket": "hour", "size_px": 400}).content)
    old_day = {"since": (now - timedelta(days=3, hours=1)).isoformat(), "until": (now - timedelta(days=2)).isoformat()}
    other = decode(client.get(url, params={**old_day, "bucket": "hour", "size_px": 400}).content)
    empty = {"since": (now - timedelta(days=10)).isoformat(), "until": (now - timedelta(days=9)).isoformat()}
    nothing = decode(client.get(url, params={**empty, "bucket": "hour", "size_px": 400}).content)
    # The density's hot colours appear where there was a violation, and not in an empty window.
    assert hot_pixels(shown) > 50 and hot_pixels(other) > 50 and hot_pixels(nothing) == 0


def decode(png: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


def hot_pixels(image: np.ndarray) -> int:
    """Pixels of the map (not the strip) in the colour map's bright yellow-orange, which nothing else uses."""
    b, g, r = (image[:400, :, k].astype(int) for k in range(3))
    return int(((r > 200) & (g > 120) & (b < 120)).sum())
