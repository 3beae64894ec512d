"""The PNG endpoints: a frame's overlay and top-down map, a camera's violation heat map."""

from __future__ import annotations

import uuid

import cv2
import httpx2 as httpx
import numpy as np
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.calibration.repository import add_calibration
from service.cameras.repository import get_camera
from service.domain import CalibrationValues
from service.frames.ingest import record_detections
from service.frames.repository import get_frame
from tests.support.app import HEIGHT_PX, WIDTH_PX, assert_problem, encoded, frame_body
from tests.support.measure import process_frame

# Two people 0.6 m apart and one far away: one violation.
PEOPLE = [
    {"shoulder": [900, 400], "ankle": [900, 700]},
    {"shoulder": [960, 400], "ankle": [960, 700]},
    {"shoulder": [1500, 350], "ankle": [1500, 600]},
]
CALIBRATION = CalibrationValues(
    status="ok", person_height_m=1.32, people_used=30, inliers=30, evidence_count=30,
    fx_px=1000.0, fy_px=1000.0, cx_px=960.0, cy_px=540.0, normal=(0.0, -0.8660254, -0.5), rho_m=4.0, noise_px=1.0,
)  # fmt: skip


def png_image(response: httpx.Response) -> np.ndarray:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    image = cv2.imdecode(np.frombuffer(response.content, dtype=np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


def measured_frame(client: TestClient, app: FastAPI, camera: str) -> dict[str, str]:
    accepted = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(PEOPLE)).json()
    with app.state.session_factory() as session:
        calibration = add_calibration(session, camera, CALIBRATION, make_current=True)
        frame = get_frame(session, camera, uuid.UUID(accepted["frame_id"]))
        process_frame(session, frame, get_camera(session, camera), calibration)  # type: ignore[arg-type]
        session.commit()
    return accepted


def test_topdown_of_a_measured_frame(client: TestClient, app: FastAPI, camera: str) -> None:
    accepted = measured_frame(client, app, camera)
    frame = client.get(accepted["url"]).json()
    assert len(frame["result"]["violations"]) == 1
    image = png_image(client.get(frame["links"]["topdown"], params={"size_px": 400, "unit": "ft"}))
    assert image.shape == (400, 400, 3)
    red = (image[:, :, 2] > 200) & (image[:, :, 1] < 80) & (image[:, :, 0] < 80)
    assert red.sum() > 20  # the violating pair is drawn in red
    assert_problem(client.get(f"{accepted['url']}/overlay.png"), 404, "posted as keypoints")


def test_topdown_before_measuring_is_409(client: TestClient, camera: str) -> None:
    accepted = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(PEOPLE)).json()
    assert_problem(client.get(f"{accepted['url']}/topdown.png"), 409, "pending")


def test_overlay_of_a_kept_image(client: TestClient, camera: str) -> None:
    body = {"image_width_px": WIDTH_PX, "image_height_px": HEIGHT_PX, "keep_images": True}
    assert client.put(f"/v1/cameras/{camera}", json=body).json()["keep_images"] is True
    jpeg = encoded(".jpg")
    accepted = client.post(f"/v1/cameras/{camera}/frames", content=jpeg, headers={"Content-Type": "image/jpeg"})
    frame = client.get(accepted.json()["url"]).json()
    assert frame["image_kept"] and "overlay" in frame["links"]
    image = png_image(client.get(frame["links"]["overlay"]))
    assert image.shape == (HEIGHT_PX, WIDTH_PX, 3)  # not measured yet: the picture with nothing to draw on it
    original = cv2.imdecode(np.frombuffer(jpeg, dtype=np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(image, original)


def test_overlay_without_kept_image_is_404(client: TestClient, app: FastAPI, camera: str) -> None:
    accepted = client.post(
        f"/v1/cameras/{camera}/frames", content=encoded(".jpg"), headers={"Content-Type": "image/jpeg"}
    ).json()
    with app.state.session_factory() as session:  # what the pose job does when it has found the people
        record_detections(session, uuid.UUID(accepted["frame_id"]), [], pose_model="test")
        session.commit()
    frame = client.get(accepted["url"]).json()
    assert (frame["status"], frame["image_kept"], frame["detections"]) == ("pending", False, [])
    assert "overlay" not in frame["links"]
    assert_problem(client.get(f"{accepted['url']}/overlay.png"), 404, "does not keep images")


def test_turning_keep_images_off_forgets_kept_images(client: TestClient, app: FastAPI, camera: str) -> None:
    body = {"image_width_px": WIDTH_PX, "image_height_px": HEIGHT_PX, "keep_images": True}
    client.put(f"/v1/cameras/{camera}", json=body)
    accepted = client.post(
        f"/v1/cameras/{camera}/frames", content=encoded(".jpg"), headers={"Content-Type": "image/jpeg"}
    ).json()
    with app.state.session_factory() as session:
        record_detections(session, uuid.UUID(accepted["frame_id"]), [], pose_model="test")
        session.commit()
    assert client.get(accepted["url"]).json()["image_kept"] is True
    client.put(f"/v1/cameras/{camera}", json={**body, "keep_images": False})
    assert client.get(accepted["url"]).json()["image_kept"] is False


def test_heatmap(client: TestClient, app: FastAPI, camera: str) -> None:
    measured_frame(client, app, camera)
    params = {"since": "2026-01-01T11:00:00Z", "until": "2026-01-01T13:00:00Z", "size_px": 300}
    image = png_image(client.get(f"/v1/cameras/{camera}/violations/heatmap.png", params=params))
    assert image.shape[1] == 300
    bad = {"since": "2026-01-01T13:00:00Z", "until": "2026-01-01T11:00:00Z"}
    assert_problem(client.get(f"/v1/cameras/{camera}/violations/heatmap.png", params=bad), 422, "before")
