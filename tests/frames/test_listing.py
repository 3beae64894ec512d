"""Finding frames: a camera's frames newest first a page at a time, filtered by status and time, and a frame looked up
by the client's own frame_id."""

from __future__ import annotations

import uuid
from collections.abc import Callable
from datetime import UTC, datetime, timedelta

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.calibration.repository import add_calibration
from service.cameras.repository import get_camera
from service.frames.listing import FramePosition
from service.frames.repository import get_frame
from tests.support.app import MIN_PEOPLE, WIDTH_PX, assert_problem, frame_body, solved, standing
from tests.support.measure import process_frame

START = datetime(2026, 5, 1, 8, 0, tzinfo=UTC)


def post(client: TestClient, camera: str, k: int, *, seconds: float | None = None, people: int = 2) -> str:
    """Frame k, taken START + `seconds` (k by default); returns its id."""
    when = START + timedelta(seconds=k if seconds is None else seconds)
    body = frame_body(standing(people), frame_id=f"f-{k}", timestamp=when.isoformat())
    response = client.post(f"/v1/cameras/{camera}/keypoints", json=body)
    assert response.status_code == 202, response.text
    return str(response.json()["frame_id"])


def pages(client: TestClient, path: str) -> list[list[dict]]:
    """Every page of a list, following next_before."""
    found, cursor = [], None
    while True:
        separator = "&" if "?" in path else "?"
        response = client.get(path if cursor is None else f"{path}{separator}before={cursor}")
        assert response.status_code == 200, response.text
        body = response.json()
        found.append(body["items"])
        cursor = body["next_before"]
        if cursor is None:
            return found


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_pages_come_newest_first_without_gaps_or_repeats(client: TestClient, camera: str) -> None:
    # Posted out of order, three of them at the very same instant: capture time then id decides.
    ids = {k: post(client, camera, k, seconds=[5, 1, 3, 3, 3, 0, 4, 2][k]) for k in range(8)}
    got = pages(client, f"/v1/cameras/{camera}/frames?limit=3")
    assert [len(page) for page in got] == [3, 3, 2]
    items = [item for page in got for item in page]
    assert len({item["frame_id"] for item in items}) == 8 == len(ids)
    keys = [(item["timestamp"], item["frame_id"]) for item in items]
    assert keys == sorted(keys, reverse=True)
    first = items[0]
    assert first["client_frame_id"] == "f-0" and first["status"] == "pending" and first["people"] == 2
    assert first["violations"] is None and first["image_kept"] is False
    assert first["url"] == f"/v1/cameras/{camera}/frames/{ids[0]}"
    assert first["links"] == {"topdown": f"{first['url']}/topdown.png"}
    # A frame arriving meanwhile, newer than the cursor, does not shift the pages already handed out.
    cursor = client.get(f"/v1/cameras/{camera}/frames?limit=3").json()["next_before"]
    post(client, camera, 8, seconds=9)
    after = client.get(f"/v1/cameras/{camera}/frames?limit=3&before={cursor}").json()["items"]
    assert [item["frame_id"] for item in after] == [item["frame_id"] for item in got[1]]


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_filters_by_status_and_time(client: TestClient, camera: str, app: FastAPI) -> None:
    ids = [post(client, camera, k, seconds=60 * k, people=3) for k in range(6)]
    with app.state.session_factory() as session:
        calibration = add_calibration(session, camera, solved(MIN_PEOPLE), make_current=True)
        for frame_id in ids[:2]:
            frame = get_frame(session, camera, uuid.UUID(frame_id))
            process_frame(session, frame, get_camera(session, camera), calibration)  # type: ignore[arg-type]
        session.commit()
    listed = client.get(f"/v1/cameras/{camera}/frames?status=done").json()["items"]
    assert [item["frame_id"] for item in listed] == ids[1::-1]
    assert all(item["violations"] is not None and item["calibration_version"] == 1 for item in listed)
    pending = client.get(f"/v1/cameras/{camera}/frames?status=pending").json()["items"]
    assert [item["frame_id"] for item in pending] == ids[:1:-1]
    since, until = (START + timedelta(minutes=1)).isoformat(), (START + timedelta(minutes=4)).isoformat()
    window = client.get(f"/v1/cameras/{camera}/frames", params={"since": since, "until": until}).json()["items"]
    assert [item["frame_id"] for item in window] == [ids[3], ids[2], ids[1]]  # [since, until)
    both = client.get(f"/v1/cameras/{camera}/frames", params={"since": since, "status": "done"}).json()["items"]
    assert [item["frame_id"] for item in both] == [ids[1]]
    unix = client.get(f"/v1/cameras/{camera}/frames", params={"until": str(int(START.timestamp()) + 60)}).json()
    assert [item["frame_id"] for item in unix["items"]] == [ids[0]]


def test_bad_cursors_and_filters_are_problems(client: TestClient, camera: str) -> None:
    post(client, camera, 0)
    path = f"/v1/cameras/{camera}/frames"
    for cursor in ("nonsense", "AAAA", "MTIz", FramePosition(START, uuid.uuid4()).encode()[:-3], "%00"):
        assert_problem(client.get(path, params={"before": cursor}), 400, "cursor")
    assert_problem(client.get(path, params={"status": "lost"}), 422)
    assert_problem(client.get(path, params={"since": "yesterday"}), 422)
    assert_problem(client.get(path, params={"limit": 0}), 422)
    assert_problem(client.get(path, params={"limit": 1001}), 422)
    assert_problem(client.get(path, params={"since": START.isoformat(), "until": START.isoformat()}), 422, "before")
    assert_problem(client.get(path, params={"frame_id": "f-0"}), 422)  # not a filter: the lookup route is
    assert_problem(client.get("/v1/cameras/nowhere/frames"), 404, "nowhere")


def test_a_cursor_round_trips_to_the_microsecond() -> None:
    for when in (START.replace(microsecond=123456), datetime(1969, 12, 31, 23, 59, 59, 999999, tzinfo=UTC)):
        position = FramePosition(when, uuid.uuid4())
        assert FramePosition.decode(position.encode()) == position


def test_lookup_by_the_clients_frame_id(client: TestClient, camera: str, app: FastAPI) -> None:
    frame_id = post(client, camera, 7)
    by_client = client.get(f"/v1/cameras/{camera}/frames/by-client-id/f-7")
    by_server = client.get(f"/v1/cameras/{camera}/frames/{frame_id}")
    assert by_client.status_code == by_server.status_code == 200
    assert by_client.json() == by_server.json()
    assert by_client.json()["client_frame_id"] == "f-7"
    # A client id that looks like a UUID is still only a client id on this route, and a service id only on the other.
    uuid_like = "0b5e6c44-5a3f-4d6e-9a59-2b8f1b3d2a10"
    body = frame_body(standing(1), frame_id=uuid_like)
    other = client.post(f"/v1/cameras/{camera}/keypoints", json=body).json()["frame_id"]
    assert client.get(f"/v1/cameras/{camera}/frames/by-client-id/{uuid_like}").json()["frame_id"] == other
    assert_problem(client.get(f"/v1/cameras/{camera}/frames/{uuid_like}"), 404, uuid_like)
    assert_problem(client.get(f"/v1/cameras/{camera}/frames/by-client-id/f-8"), 404, "f-8")
    assert_problem(client.get(f"/v1/cameras/{camera}/frames/by-client-id/bad%20id"), 422)
    assert_problem(client.get("/v1/cameras/nowhere/frames/by-client-id/f-7"), 404, "nowhere")


def test_scoped_keys_list_only_their_cameras(
    client: TestClient, camera: str, client_for: Callable[[str], TestClient]
) -> None:
    assert (
        client.put("/v1/cameras/other", json={"image_width_px": WIDTH_PX, "image_height_px": 1080}).status_code == 201
    )
    post(client, "other", 1)
    post(client, camera, 2)
    token = client.post("/v1/keys", json={"name": "gateway", "cameras": [camera]}).json()["token"]
    scoped = client_for(token)
    assert [item["client_frame_id"] for item in scoped.get(f"/v1/cameras/{camera}/frames").json()["items"]] == ["f-2"]
    assert_problem(scoped.get("/v1/cameras/other/frames"), 403)
    assert_problem(scoped.get("/v1/cameras/other/frames/by-client-id/f-1"), 403)
    assert_problem(scoped.get("/v1/cameras/missing/frames"), 403)  # existence is not revealed
