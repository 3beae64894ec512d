"""One client's bad frame costs nobody else anything: every number is checked before anything is packed, and a
burst of good and poisoned frames from several keys and cameras is answered frame by frame (issue 14).

The burst here is in process (the real app, its frame writer and SQLite); tests/faults/test_burst.py sends one to a
real `posemetry serve`.
"""

from __future__ import annotations

import json
import random
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from service.frames.schemas import COORDINATE_LIMIT_PX
from service.store.models import Frame, Observation
from tests.support.app import ADMIN_KEY, HEIGHT_PX, WIDTH_PX, assert_problem, bearer, frame_body, standing


def issue_keypoints() -> list[list[float]]:
    """The issue's frame: 17 rows of [900, 300 + 10 i, 0.9], row 0 replaced below."""
    return [[900.0, 300.0 + 10 * i, 0.9] for i in range(17)]


def test_a_score_zero_keypoint_beyond_float32_is_refused_not_a_500(client: TestClient, camera: str) -> None:
    """The issue's reproduction: [1e39, 0, 0] as keypoint 0 was packed as float32, overflowed, and failed the
    whole write batch with 500."""
    keypoints = issue_keypoints()
    keypoints[0] = [1e39, 0, 0]
    response = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([{"keypoints": keypoints}]))
    body = assert_problem(response, 422, "body.people[0].keypoints[0]")
    assert {error["field"] for error in body["errors"]} == {"body.people[0].keypoints[0][0]"}
    good = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([{"keypoints": issue_keypoints()}]))
    assert good.status_code == 202, good.text


BAD_NUMBERS = [1e39, -1e39, 1e300, COORDINATE_LIMIT_PX * 1.01, 5 * WIDTH_PX]


def _keypoints_with(k: int, axis: int, value: float, score: float) -> dict[str, Any]:
    keypoints = issue_keypoints()
    keypoints[k] = [900.0, 400.0, score]
    keypoints[k][axis] = value
    return {"keypoints": keypoints}


def _places(value: float) -> list[tuple[str, dict[str, Any]]]:
    """Every place a pixel number sits in a posted person, with the value there."""
    return [
        ("keypoint x, score 0", _keypoints_with(0, 0, value, 0.0)),
        ("keypoint y, score 0", _keypoints_with(16, 1, value, 0.0)),
        ("keypoint x, score 0.9", _keypoints_with(5, 0, value, 0.9)),
        ("shoulder x", {"shoulder": [value, 400.0], "ankle": [900.0, 700.0]}),
        ("shoulder y", {"shoulder": [900.0, value], "ankle": [900.0, 700.0]}),
        ("ankle x", {"shoulder": [900.0, 400.0], "ankle": [value, 700.0]}),
        ("ankle y", {"shoulder": [900.0, 400.0], "ankle": [900.0, value]}),
    ]


@pytest.mark.parametrize("value", BAD_NUMBERS)
@pytest.mark.parametrize("route", ["keypoints", "distances"])
def test_every_out_of_range_number_is_a_422_wherever_it_sits(
    client: TestClient, camera: str, route: str, value: float
) -> None:
    good = standing(2)
    for place, person in _places(value):
        body = frame_body([*good, person]) if route == "keypoints" else {"people": [*good, person]}
        response = client.post(f"/v1/cameras/{camera}/{route}", json=body)
        problem = assert_problem(response, 422)
        assert all(error["field"].startswith("body.people[2].") for error in problem["errors"]), (place, problem)
    with client.app.state.session_factory() as session:  # type: ignore[attr-defined]
        assert session.scalar(select(func.count()).select_from(Frame)) == 0


def test_the_coordinate_limit_is_published(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()["components"]["schemas"]
    point = schema["PersonObservation"]["properties"]["shoulder"]["anyOf"][0]["prefixItems"][0]
    assert (point["minimum"], point["maximum"]) == (-COORDINATE_LIMIT_PX, COORDINATE_LIMIT_PX)


# --------------------------------------------------------------------------------------------------- a burst


def _poisoned(rng: random.Random) -> dict[str, Any]:
    """A frame no client should send: a bad number somewhere, a frame of too many people, or a broken person."""
    value = rng.choice([*BAD_NUMBERS, float("-inf")])
    choice = rng.randrange(4)
    if choice == 0:
        return frame_body([*standing(3), rng.choice(_places(value))[1]])
    if choice == 1:
        return frame_body(standing(1) * 51)  # over max_people_per_frame (50)
    if choice == 2:
        return frame_body([{"keypoints": issue_keypoints()[:16]}])
    return frame_body([{"shoulder": [900.0, 400.0], "keypoints": issue_keypoints()}])


def test_a_burst_of_good_and_poisoned_frames_from_several_keys_loses_no_good_frame(
    app: FastAPI, client: TestClient
) -> None:
    cameras = ["cam-a", "cam-b", "cam-c"]
    tokens = {}
    for camera_id in cameras:
        assert client.put(f"/v1/cameras/{camera_id}", json={"image_width_px": WIDTH_PX, "image_height_px": HEIGHT_PX})
        created = client.post("/v1/keys", json={"name": camera_id, "cameras": [camera_id]})
        tokens[camera_id] = created.json()["token"]
    rng = random.Random(14)
    posts: list[tuple[str, str, dict[str, Any], bool]] = []
    for k in range(240):
        camera_id = rng.choice(cameras)
        good = rng.random() < 0.8
        body = frame_body(standing(rng.randint(0, 6)), frame_id=f"f-{k}") if good else _poisoned(rng)
        token = tokens[camera_id] if rng.random() < 0.7 else ADMIN_KEY
        posts.append((camera_id, token, body, good))

    clients = {token: TestClient(app, headers=bearer(token)) for token in {*tokens.values(), ADMIN_KEY}}

    def post(item: tuple[str, str, dict[str, Any], bool]) -> int:
        camera_id, token, body, _good = item
        content = json.dumps(body)  # -Infinity is spelled as Python's JSON reader takes it
        headers = {"content-type": "application/json"}
        return clients[token].post(f"/v1/cameras/{camera_id}/keypoints", content=content, headers=headers).status_code

    with ThreadPoolExecutor(16) as pool:
        statuses = list(pool.map(post, posts))
    by_kind = Counter((good, status) for (_, _, _, good), status in zip(posts, statuses, strict=True))
    print(f"\nin-process burst: {dict(by_kind)}")
    assert {status for (good, status) in by_kind if good} == {202}
    assert {status for (good, status) in by_kind if not good} <= {413, 422}
    with app.state.session_factory() as session:
        stored = Counter(session.scalars(select(Frame.client_frame_id)))
        people = session.scalar(select(func.count()).select_from(Observation))
    wanted = {body["frame_id"] for _, _, body, good in posts if good}
    assert set(stored) == wanted and set(stored.values()) == {1}
    assert people == sum(len(body["people"]) for _, _, body, good in posts if good)


# --------------------------------------------------------------------------------------------------- other numbers


def _integer_query_parameters(schema: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(method, path, parameter) of every integer query parameter of the contract."""
    found = []
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            for parameter in operation.get("parameters", []):
                types = [parameter["schema"], *parameter["schema"].get("anyOf", [])]
                if parameter["in"] == "query" and any(t.get("type") == "integer" for t in types):
                    found.append((method.upper(), path, parameter["name"]))
    return found


def test_every_integer_query_parameter_refuses_what_the_database_cannot_hold(client: TestClient, camera: str) -> None:
    """`before=10**23` on the calibration history overflowed SQLite's INTEGER: a 500, found while auditing this."""
    found = _integer_query_parameters(client.get("/openapi.json").json())
    assert ("GET", "/v1/cameras/{camera_id}/calibration/history", "before") in found
    for method, path, name in found:
        url = path.replace("{camera_id}", camera).replace("{frame_id}", "0" * 8 + "-0000-0000-0000-" + "0" * 12)
        for value in (10**23, -(10**23), 2**63):
            response = client.request(method, f"{url}?{name}={value}")
            assert 400 <= response.status_code < 500, (method, url, name, value, response.text)
