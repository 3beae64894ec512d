"""Cameras: idempotent PUT, defaults and units, list, get, delete, and what a settings change does."""

from __future__ import annotations

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.calibration.repository import add_calibration
from service.cameras.repository import delete_camera
from service.geometry import DEFAULT_HEIGHT_M
from service.store.models import Camera
from tests.support.app import CAMERA, assert_problem, frame_body, solved, standing
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


def test_the_camera_model_round_trips_and_a_put_replaces_it(client: TestClient) -> None:
    body = {
        "image_width_px": 1920,
        "image_height_px": 1080,
        "principal_point_px": [1010.5, 480],
        "known_focal_px": [1400, 1410],
        "distortion": {"model": "opencv", "coefficients": [-0.2, 0.05, 0.001, -0.001]},
        "camera_height_m": 6.5,
    }
    camera = client.put("/v1/cameras/lobby", json=body).json()
    assert camera["principal_point_px"] == [1010.5, 480]
    assert camera["known_focal_px"] == [1400, 1410]
    assert camera["distortion"] == {"model": "opencv", "coefficients": [-0.2, 0.05, 0.001, -0.001]}
    assert camera["camera_height_m"] == 6.5 and camera["camera_height_tolerance_m"] == 0.1
    assert client.get("/v1/cameras/lobby").json() == camera
    single = client.put(
        "/v1/cameras/lobby", json={"image_width_px": 1920, "image_height_px": 1080, "known_focal_px": 1400}
    )
    assert single.json()["known_focal_px"] == 1400
    assert single.json()["principal_point_px"] is None and single.json()["distortion"] is None


@pytest.mark.parametrize(
    ("extra", "field", "fragment"),
    [
        ({"principal_point_px": [2000, 500]}, "body", "outside the 1920x1080 image"),
        ({"principal_point_px": [-1, 500]}, "body", "outside"),
        ({"principal_point_px": [960]}, "body.principal_point_px", ""),
        ({"principal_point_px": [960, "NaN"]}, "body.principal_point_px[1]", ""),
        ({"known_focal_px": 50}, "body", "96-96000 px"),
        ({"known_focal_px": [1000, 1e7]}, "body", "known_focal_px"),
        ({"known_focal_px": -3}, "body.known_focal_px", ""),
        ({"known_focal_px": [1000, 1000, 1000]}, "body.known_focal_px", ""),
        ({"distortion": {"model": "fisheye", "coefficients": [0, 0, 0, 0]}}, "body.distortion.model", ""),
        ({"distortion": {"model": "opencv", "coefficients": [0.1, 0.2, 0]}}, "body.distortion.coefficients", ""),
        ({"distortion": {"model": "opencv", "coefficients": [0, 0, 0, 0, 0, 0]}}, "body.distortion.coefficients", ""),
        ({"camera_height_m": 0}, "body.camera_height_m", ""),
        ({"camera_height_m": 5, "camera_height_tolerance_m": 0}, "body.camera_height_tolerance_m", ""),
    ],
)  # fmt: skip
def test_bad_camera_model_values_are_422(
    client: TestClient, extra: dict[str, object], field: str, fragment: str
) -> None:
    body = {"image_width_px": 1920, "image_height_px": 1080, **extra}
    problem = assert_problem(client.put("/v1/cameras/x", json=body), 422, field, fragment)
    assert any(e["field"].startswith(field) for e in problem["errors"]), problem
    assert client.get("/v1/cameras/x").status_code == 404


def test_a_new_principal_point_resets_the_calibration_and_forces_a_resolve_on_the_same_evidence(
    client: TestClient, camera: str, app: FastAPI, dispatcher: RecordingDispatcher
) -> None:
    client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(3)))
    with app.state.session_factory() as session:
        add_calibration(session, camera, solved(3), make_current=True)
        session.commit()
    size = {"image_width_px": 1920, "image_height_px": 1080}
    client.put(f"/v1/cameras/{camera}", json={**size, "camera_height_m": 5.0})
    assert dispatcher.calibrations == [(CAMERA, True)]  # a prior: re-solve, the current one stays in use
    assert client.get(f"/v1/cameras/{camera}/calibration").json()["status"] == "calibrated"
    client.put(f"/v1/cameras/{camera}", json={**size, "camera_height_m": 5.0, "principal_point_px": [900, 600]})
    assert dispatcher.calibrations == [(CAMERA, True), (CAMERA, True)]
    status = client.get(f"/v1/cameras/{camera}/calibration").json()
    assert status["status"] != "calibrated" and status["version"] is None  # never mixed with the old solution
    assert status["epoch"] == 1  # the same view: the same epoch, whose people the re-solve uses
    assert client.get(f"/v1/cameras/{camera}").json()["usable_evidence_count"] == 3
