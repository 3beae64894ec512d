"""A client frame id names one frame: a true retry is 200 with that frame, other content under it is 409 (issue 14).

"The same content" (README, Idempotency): the same instant and the same people in order, each as stored (keypoints
at float32 precision, centres as float64), however the JSON spelled them; for an image, the same bytes, and the same
timestamp when the retry gives one.
"""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import update

from service.frames.ingest import NewKeypointFrame
from service.frames.schemas import PersonObservation
from service.frames.service import people_for_camera
from service.frames.writer import FrameWriter
from service.store.models import Frame, utc_now
from tests.support.app import assert_problem, coco_person, encoded, frame_body, standing


def post(client: TestClient, camera: str, body: dict[str, Any] | str) -> Any:
    if isinstance(body, str):  # the JSON text as given, to vary how numbers and keys are spelled
        return client.post(
            f"/v1/cameras/{camera}/keypoints", content=body, headers={"content-type": "application/json"}
        )
    return client.post(f"/v1/cameras/{camera}/keypoints", json=body)


def test_a_true_retry_is_the_same_frame_however_the_json_spells_it(client: TestClient, camera: str) -> None:
    people = [{"keypoints": coco_person((900, 400), (900, 700))}, {"shoulder": [500, 420], "ankle": [505, 690]}]
    first = post(client, camera, frame_body(people, frame_id="f-1"))
    assert first.status_code == 202, first.text
    # Integers for floats, exponents, reordered keys, another time zone for the same instant: the same content.
    respelled = json.dumps(
        {
            "people": [
                {"keypoints": [[int(x) if x == int(x) else x, y, s] for x, y, s in people[0]["keypoints"]]},
                {"ankle": [5.05e2, 690.0], "shoulder": [500.0, 4.2e2]},
            ],
            "frame_id": "f-1",
            "timestamp": "2026-01-01T13:00:00+01:00",
        }
    )
    retry = post(client, camera, respelled)
    assert retry.status_code == 200, retry.text
    assert retry.json()["frame_id"] == first.json()["frame_id"] and retry.json()["created"] is False


@pytest.mark.parametrize(
    "change",
    [
        "another person",
        "a moved keypoint",
        "a score",
        "a later timestamp",
        "centres for keypoints",
        "people reordered",
        "a track id given",
        "another track id",
    ],
)
def test_the_same_frame_id_with_other_content_is_409_naming_the_stored_frame(
    client: TestClient, camera: str, change: str
) -> None:
    people = standing(2)
    people[1]["track_id"] = "7"
    first = post(client, camera, frame_body(people, frame_id="f-1"))
    assert first.status_code == 202
    other: dict[str, Any] = frame_body(json.loads(json.dumps(people)), frame_id="f-1")
    if change == "another person":
        other["people"] += standing(1, x0=1200)
    elif change == "a moved keypoint":
        other["people"][1]["keypoints"][3][0] += 0.5
    elif change == "a score":
        other["people"][0]["keypoints"][0][2] = 0.1
    elif change == "a later timestamp":
        other["timestamp"] = "2026-01-01T12:00:00.000001Z"
    elif change == "a track id given":
        other["people"][0]["track_id"] = "8"
    elif change == "another track id":
        other["people"][1]["track_id"] = "8"
    elif change == "centres for keypoints":
        other["people"][0] = {"shoulder": [300.0, 400.0], "ankle": [300.0, 700.0]}
    else:
        other["people"].reverse()
    conflict = post(client, camera, other)
    body = assert_problem(conflict, 409, "f-1", first.json()["url"])
    assert body["type"].endswith("/frame-id-conflict")
    assert (body["frame_id"], body["client_frame_id"], body["url"]) == (
        first.json()["frame_id"],
        "f-1",
        first.json()["url"],
    )
    assert conflict.headers["location"] == first.json()["url"]
    # Nothing of the conflicting post was stored; the first frame is intact, and a true retry still works.
    stored = client.get(first.json()["url"]).json()
    assert stored["people"] == 2
    assert post(client, camera, frame_body(people, frame_id="f-1")).status_code == 200
    assert client.get(f"/v1/cameras/{camera}").json()["usable_evidence_count"] == 2


def test_a_frame_stored_before_digests_is_answered_as_a_retry(app: FastAPI, client: TestClient, camera: str) -> None:
    """Frames stored before revision 0007 have no digest: a reuse of their id cannot be judged, and stays 200."""
    first = post(client, camera, frame_body(standing(2), frame_id="old"))
    with app.state.session_factory() as session:
        session.execute(update(Frame).values(content_sha256=None))
        session.commit()
    assert post(client, camera, frame_body(standing(3), frame_id="old")).status_code == 200
    assert client.get(first.json()["url"]).json()["people"] == 2


def test_a_reused_id_inside_one_write_batch_is_caught_too(app: FastAPI, camera: str) -> None:
    """Two posts of one frame id with different people in the same group commit: the second is answered with the
    first frame, whose digest tells the API that it is a conflict."""
    cached = app.state.camera_cache.get(camera)
    frames = [
        NewKeypointFrame(
            cached,
            utc_now(),
            people_for_camera([PersonObservation.model_validate(p) for p in people], cached, app.state.settings),
            "x",
        )
        for people in (standing(2), standing(3))
    ]
    writer: FrameWriter = app.state.frame_writer
    (first, created), (again, again_created) = writer.store_batch(frames)  # type: ignore[misc]
    assert created and not again_created and again.id == first.id
    assert first.content_sha256 == frames[0].content_sha256 != frames[1].content_sha256


# --------------------------------------------------------------------------------------------------- images


def post_image(client: TestClient, camera: str, data: bytes, query: str) -> Any:
    kind = "image/png" if data.startswith(b"\x89PNG") else "image/jpeg"
    return client.post(f"/v1/cameras/{camera}/frames?{query}", content=data, headers={"content-type": kind})


def test_image_frames_retry_on_the_same_bytes_and_conflict_on_others(client: TestClient, camera: str) -> None:
    image, other = encoded(".jpg"), encoded(".png")
    first = post_image(client, camera, image, "frame_id=img&timestamp=2026-01-01T12:00:00Z")
    assert first.status_code == 202, first.text
    assert post_image(client, camera, image, "frame_id=img&timestamp=2026-01-01T12:00:00Z").status_code == 200
    assert post_image(client, camera, image, "frame_id=img").status_code == 200  # no timestamp: nothing to compare
    body = assert_problem(post_image(client, camera, other, "frame_id=img"), 409, first.json()["url"])
    assert body["frame_id"] == first.json()["frame_id"]
    later = post_image(client, camera, image, "frame_id=img&timestamp=2026-01-01T12:00:01Z")
    assert_problem(later, 409, "frame_id 'img'")
