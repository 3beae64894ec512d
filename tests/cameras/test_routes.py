"""Cameras: idempotent PUT, defaults and units, list, get, delete, and what a settings change does."""

from __future__ import annotations

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.cameras.repository import delete_camera
from service.geometry import DEFAULT_HEIGHT_M
from service.store.models import Camera
from tests.support.app import CAMERA, assert_problem, frame_body, standing
from tests.support.dispatch import RecordingDispatcher


def test_put_creates_then_updates_with_documented_defaults(client: TestClient) -> None:
    body = {"image_width_px": 1280, "image_height_px": 720}
    created = client.put("/v1/cameras/door.2", json=body)
    assert created.status_code == 201
    assert created.headers["location"] == "/v1/cameras/door.2"
    camera = created.json()
    assert camera["person_height_m"] == DEFAULT_HEIGHT_M
    assert camera["equal_focal"] is True
    assert camera["distance_threshold_m"] == pytest.approx(1.8288)
    assert camera["distance_threshold_ft"] == pytest.approx(6.0)
    assert camera["known_focal_px"] is None
    again = client.put("/v1/cameras/door.2", json=body)
    assert again.status_code == 200
    assert again.json()["created_at"] == camera["created_at"]


@pytest.mark.parametrize(
    ("threshold", "metres"), [({"value": 2, "unit": "m"}, 2.0), ({"value": 5, "unit": "ft"}, 1.524)]
)
def test_threshold_in_metres_or_feet(client: TestClient, threshold: dict[str, object], metres: float) -> None:
    body = {"image_width_px": 640, "image_height_px": 480, "distance_threshold": threshold, "known_focal_px": 500}
    camera = client.put("/v1/cameras/c", json=body).json()
    assert camera["distance_threshold_m"] == pytest.approx(metres)
    assert camera["known_focal_px"] == 500


@pytest.mark.parametrize("feet", [6, 5, 3.5, 10, 13.1])
def test_thresholds_in_feet_read_back_as_written(client: TestClient, feet: float) -> None:
    """6 ft is 1.8288 m, not the 1.8288000000000002 that binary floating point makes of 6 x 0.3048."""
    body = {"image_width_px": 640, "image_height_px": 480, "distance_threshold": {"value": feet, "unit": "ft"}}
    response = client.put("/v1/cameras/c", json=body)
    camera = response.json()
    assert camera["distance_threshold_ft"] == feet
    assert camera["distance_threshold_m"] == float(f"{feet * 0.3048:.9f}")
    assert len(repr(camera["distance_threshold_m"])) <= 12, response.text


def test_a_threshold_stored_unrounded_reads_back_rounded(client: TestClient, app: FastAPI) -> None:
    """Cameras stored before conversions were rounded hold 6 x 0.3048 as it came out."""
    client.put("/v1/cameras/old", json={"image_width_px": 640, "image_height_px": 480})
    with app.state.session_factory() as session:
        session.get(Camera, "old").distance_threshold_m = 6 * 0.3048  # type: ignore[union-attr]
        session.commit()
    app.state.camera_cache.forget("old")
    text = client.get("/v1/cameras/old").text
    assert '"distance_threshold_m":1.8288,' in text and '"distance_threshold_ft":6.0,' in text, text


def test_list_get_delete(client: TestClient) -> None:
    for name in ("b", "a", "c"):
        client.put(f"/v1/cameras/{name}", json={"image_width_px": 640, "image_height_px": 480})
    page = client.get("/v1/cameras", params={"limit": 2}).json()
    assert [c["id"] for c in page["items"]] == ["a", "b"]
    assert page["next_after"] == "b"
    rest = client.get("/v1/cameras", params={"limit": 2, "after": "b"}).json()
    assert [c["id"] for c in rest["items"]] == ["c"] and rest["next_after"] is None
    assert client.get("/v1/cameras/a").json()["url"] == "/v1/cameras/a"
    assert client.delete("/v1/cameras/a").status_code == 204
    assert_problem(client.get("/v1/cameras/a"), 404, "no camera 'a'", "PUT")
    assert_problem(client.delete("/v1/cameras/a"), 404, "no camera")


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"image_width_px": 0, "image_height_px": 480}, "body.image_width_px"),
        ({"image_width_px": 640, "image_height_px": 480, "zoom": 2}, "body.zoom"),
        ({"image_width_px": 640, "image_height_px": 480, "person_height_m": 9}, "body.person_height_m"),
        ({"image_width_px": 640, "image_height_px": 480, "distance_threshold": {"value": 6, "unit": "yd"}},
         "body.distance_threshold.unit"),
        ({"image_width_px": 640, "image_height_px": 480, "distance_threshold_m": 2}, "body.distance_threshold_m"),
        ({"image_width_px": 640}, "body.image_height_px"),
    ],
)  # fmt: skip
def test_bad_camera_settings_name_the_field(client: TestClient, body: dict[str, object], field: str) -> None:
    problem = assert_problem(client.put("/v1/cameras/x", json=body), 422, field)
    assert any(e["field"] == field for e in problem["errors"])


@pytest.mark.parametrize("camera_id", ["-lead", "has space", "a" * 65, "semi;colon", "%C3%A9t%C3%A9"])
def test_unsafe_camera_ids_are_refused(client: TestClient, camera_id: str) -> None:
    response = client.put(f"/v1/cameras/{camera_id}", json={"image_width_px": 640, "image_height_px": 480})
    assert_problem(response, 422, "path.camera_id")


def test_new_image_size_drops_evidence_and_new_prior_asks_for_a_resolve(
    client: TestClient, camera: str, dispatcher: RecordingDispatcher
) -> None:
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(3)))
    assert client.get(f"/v1/cameras/{camera}").json()["usable_evidence_count"] == 3
    client.put(f"/v1/cameras/{camera}", json={"image_width_px": 1920, "image_height_px": 1080, "person_height_m": 1.4})
    assert dispatcher.calibrations == [(CAMERA, True)]
    assert client.get(f"/v1/cameras/{camera}").json()["usable_evidence_count"] == 3
    client.put(f"/v1/cameras/{camera}", json={"image_width_px": 1280, "image_height_px": 720})
    assert client.get(f"/v1/cameras/{camera}").json()["usable_evidence_count"] == 0


def test_keypoint_frames_see_a_new_image_size_at_once(client: TestClient, camera: str) -> None:
    """The API caches cameras for accepting frames (POSEMETRY_CAMERA_CACHE_TTL_S); its own changes apply at once."""
    far_right = {"shoulder": [1900, 300], "ankle": [1900, 450]}  # inside 1920 x 1080, far outside 640 x 480
    client.put(f"/v1/cameras/{camera}", json={"image_width_px": 640, "image_height_px": 480})
    assert_problem(client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([far_right])), 422)
    client.put(f"/v1/cameras/{camera}", json={"image_width_px": 1920, "image_height_px": 1080})
    assert client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([far_right])).status_code == 202
    assert client.delete(f"/v1/cameras/{camera}").status_code == 204
    assert_problem(client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([far_right])), 404)


def test_a_camera_deleted_by_another_process_is_404_for_frames(client: TestClient, camera: str, app: FastAPI) -> None:
    assert client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2))).status_code == 202  # cached
    with app.state.session_factory() as session, session.begin():
        delete_camera(session, camera)  # past this process's cache, as another API process would
    assert_problem(client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2))), 404, camera)
