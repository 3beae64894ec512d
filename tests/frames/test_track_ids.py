"""A posted person's `track_id`: checked like a frame id, stored on the person, part of the frame's content."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select

from service.domain import PersonIn
from service.frames.digests import keypoint_frame_digest
from service.store.models import Observation
from tests.support.app import assert_problem, frame_body, standing


def _post(client: TestClient, camera: str, body: dict[str, Any]) -> Any:
    return client.post(f"/v1/cameras/{camera}/keypoints", json=body)


def test_track_ids_are_stored_on_their_people(client: TestClient, camera: str, app: FastAPI) -> None:
    people = standing(3)
    people[0]["track_id"] = "2026-01-01T12:00:00Z:17"
    people[2]["track_id"] = "x" * 64
    people.append({"shoulder": [1000.0, 400.0], "ankle": [1000.0, 700.0], "track_id": "centres.1"})
    response = _post(client, camera, frame_body(people))
    assert response.status_code == 202, response.text
    with app.state.session_factory() as session:
        stored = session.execute(
            select(Observation.person_index, Observation.client_track_id).order_by(Observation.person_index)
        ).all()
    assert [tuple(row) for row in stored] == [
        (0, "2026-01-01T12:00:00Z:17"),
        (1, None),
        (2, "x" * 64),
        (3, "centres.1"),
    ]


@pytest.mark.parametrize("track_id", ["", "x" * 65, "-leading-dash", "a b", "<script>alert(1)</script>", "é", 17])
def test_a_bad_track_id_is_422_naming_the_field_without_echoing_it(
    client: TestClient, camera: str, track_id: object
) -> None:
    people = standing(2)
    people[1]["track_id"] = track_id
    response = _post(client, camera, frame_body(people))
    problem = assert_problem(response, 422, "body.people[1].track_id")
    assert [error["field"] for error in problem["errors"]] == ["body.people[1].track_id"]
    if isinstance(track_id, str) and track_id:
        assert track_id not in response.text
    assert client.get(f"/v1/cameras/{camera}").json()["usable_evidence_count"] == 0


def test_one_track_id_for_two_people_of_a_frame_is_422(client: TestClient, camera: str) -> None:
    people = standing(3)
    people[0]["track_id"] = people[2]["track_id"] = "7"
    problem = assert_problem(_post(client, camera, frame_body(people)), 422, "people 0 and 2", "same track_id")
    assert [error["type"] for error in problem["errors"]] == ["duplicate_track_id"]
    people[2]["track_id"] = "8"
    assert _post(client, camera, frame_body(people)).status_code == 202


def test_a_retry_with_the_same_track_ids_is_the_same_frame(client: TestClient, camera: str) -> None:
    people = standing(2)
    people[0]["track_id"] = "7"
    first = _post(client, camera, frame_body(people, frame_id="f-1"))
    assert first.status_code == 202
    retry = _post(client, camera, frame_body(people, frame_id="f-1"))
    assert retry.status_code == 200 and retry.json()["frame_id"] == first.json()["frame_id"]


def test_people_without_track_ids_keep_the_digest_frames_were_stored_with() -> None:
    """Digests stored before track ids existed must still recognise a retry: pinned to the value the code before
    them gave (a person posted as centres without an ankle, one as keypoints)."""
    at = datetime(2026, 1, 1, 12, tzinfo=UTC)
    keypoints = [[float(i), float(2 * i), 0.5] for i in range(17)]
    people = [PersonIn((300.0, 400.0), (300.0, 700.0)), PersonIn((500.0, 420.0), None, keypoints=keypoints)]
    assert keypoint_frame_digest(at, people) == "539c3cc63e61ac3e75cd8d57af7c1b8168a8a08216bc52b559fd7ce44ffc356d"
    tracked = [PersonIn((300.0, 400.0), (300.0, 700.0), track_id="a"), people[1]]
    assert keypoint_frame_digest(at, tracked) != keypoint_frame_digest(at, people)
