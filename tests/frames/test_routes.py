"""Keypoint frames: stored then dispatched, idempotent retries, 503 without losing data, and results."""

from __future__ import annotations

import uuid

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import event, func, select

from service.calibration.repository import add_calibration
from service.calibration.service import DueSolves
from service.cameras.repository import get_camera
from service.dispatch import DispatchUnavailableError
from service.domain import CalibrationValues, CameraCounters
from service.frames.repository import get_frame, pending_frames
from service.frames.routes import dispatch_stored
from service.frames.schemas import FrameOut
from service.store.models import Frame, Observation
from tests.support.app import MIN_PEOPLE, assert_problem, coco_person, frame_body, standing
from tests.support.dispatch import RecordingDispatcher
from tests.support.measure import process_frame


def observation_count(app: FastAPI) -> int:
    with app.state.session_factory() as session:
        return int(session.execute(select(func.count()).select_from(Observation)).scalar_one())


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_post_stores_dispatches_and_reads_back(
    client: TestClient, camera: str, app: FastAPI, dispatcher: RecordingDispatcher
) -> None:
    people = [*standing(2), {"shoulder": [900, 300], "ankle": None}, {"shoulder": [1000, 300], "ankle": [1000, 600]}]
    response = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(people))
    assert response.status_code == 202, response.text
    accepted = response.json()
    assert accepted["status"] == "pending" and accepted["created"] is True and accepted["people"] == 4
    assert response.headers["location"] == accepted["url"] == f"/v1/cameras/{camera}/frames/{accepted['frame_id']}"
    assert dispatcher.frames == [(camera, uuid.UUID(accepted["frame_id"]))]
    frame = client.get(accepted["url"]).json()
    assert frame["status"] == "pending" and frame["result"] is None and frame["people"] == 4
    assert frame["timestamp"].startswith("2026-01-01T12:00:00")
    assert observation_count(app) == 4
    # Three usable people: the hidden-ankle one is stored (for measurement) but is not evidence.
    assert client.get(f"/v1/cameras/{camera}").json()["usable_evidence_count"] == 3


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_retry_with_the_same_client_frame_id_is_the_same_frame(
    client: TestClient, camera: str, app: FastAPI, dispatcher: RecordingDispatcher
) -> None:
    first = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(3), frame_id="f-1"))
    again = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(3), frame_id="f-1"))
    assert first.status_code == 202 and again.status_code == 200
    assert again.json()["frame_id"] == first.json()["frame_id"]
    assert again.json()["created"] is False
    assert observation_count(app) == 3
    other = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(3), frame_id="f-2"))
    assert other.json()["frame_id"] != first.json()["frame_id"]
    assert observation_count(app) == 6
    # A still-pending frame is dispatched again on retry: that is how a client recovers from a 503.
    assert len(dispatcher.frames) == 3


def test_queue_down_answers_503_and_keeps_the_frame(
    client: TestClient, camera: str, app: FastAPI, dispatcher: RecordingDispatcher
) -> None:
    dispatcher.fail = True
    response = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2), frame_id="lost"))
    problem = assert_problem(response, 503, "queue", "stored")
    frame = client.get(problem["url"])
    assert frame.status_code == 200 and frame.json()["status"] == "pending"
    with app.state.session_factory() as session:
        assert [f.id for f in pending_frames(session, camera)] == [uuid.UUID(problem["frame_id"])]
    assert observation_count(app) == 2
    dispatcher.fail = False
    retry = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(2), frame_id="lost"))
    assert retry.status_code == 200 and retry.json()["frame_id"] == problem["frame_id"]
    assert dispatcher.frames == [(camera, uuid.UUID(problem["frame_id"]))]
    assert observation_count(app) == 2


def test_a_write_batch_makes_one_queue_call_naming_each_camera_once() -> None:
    def stored(camera_id: str, status: str = "pending", created: bool = True) -> tuple[Frame, bool]:
        return Frame(id=uuid.uuid4(), camera_id=camera_id, status=status), created

    batch = [stored("a"), stored("b"), stored("a"), stored("c", "done", created=False), stored("b")]
    dispatcher = RecordingDispatcher()
    assert dispatch_stored(dispatcher, None, batch) == [None] * 5
    # The answered retry ("c") is not asked for; each camera is named by its first frame of the batch.
    assert dispatcher.frames == [("a", batch[0][0].id), ("b", batch[1][0].id)]

    down = RecordingDispatcher(fail=True)
    errors = dispatch_stored(down, None, batch)
    assert isinstance(errors[0], DispatchUnavailableError)
    assert [error is errors[0] for error in errors] == [True, True, True, False, True]
    assert errors[3] is None  # a retry of a frame already measured needs no queue: its post is answered as usual
    assert dispatch_stored(down, None, [stored("c", "done", created=False)]) == [None]  # and makes no call at all


def test_a_frame_makes_one_queue_call(client: TestClient, camera: str, dispatcher: RecordingDispatcher) -> None:
    """The hot path nudges measuring, and asks for a solve only when the frame's people make one due."""
    accepted = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(MIN_PEOPLE - 1))).json()
    assert dispatcher.frames == [(camera, uuid.UUID(accepted["frame_id"]))]
    assert dispatcher.calibrations == []


@pytest.mark.both_backends
def test_the_frame_that_makes_a_solve_due_asks_for_it_once(
    client: TestClient, camera: str, app: FastAPI, dispatcher: RecordingDispatcher
) -> None:
    """Not the measuring job, which runs behind the posts under load: the API asks when the evidence is stored, and
    once per solve (the frames posted while it waits do not ask again)."""
    post = lambda n: client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(n)))  # noqa: E731
    assert post(MIN_PEOPLE - 1).status_code == 202 and dispatcher.calibrations == []
    assert post(1).status_code == 202 and dispatcher.calibrations == [(camera, False)]
    assert post(3).status_code == 202 and dispatcher.calibrations == [(camera, False)]
    values = CalibrationValues(
        status="failed", reason="too thin", person_height_m=1.32, people_used=8, inliers=0, evidence_count=8
    )
    with app.state.session_factory() as session:
        add_calibration(session, camera, values, make_current=False)  # the solve ran on 8 people (failed ones count)
        session.commit()
    assert post(7).status_code == 202 and dispatcher.calibrations == [(camera, False)]  # 15 < 2 x 8
    assert post(1).status_code == 202 and dispatcher.calibrations == [(camera, False)] * 2  # 16: due again


@pytest.mark.both_backends
def test_the_due_check_reads_no_counters_the_batch_handed_over(camera: str, app: FastAPI) -> None:
    """The write batch hands over the counters its transaction left (ingest.add_keypoint_frames): for those cameras
    the after-commit check runs no statement once their next target is known, and reads only what it was not given."""
    statements: list[str] = []
    engine = app.state.engine
    # (conn, cursor, statement, ...): the queries, not SQLite's BEGIN.
    listener = lambda *args: statements.append(args[2]) if args[2].startswith("SELECT") else None  # noqa: E731
    due = DueSolves(app.state.settings, app.state.read_session_factory, recording := RecordingDispatcher())
    event.listen(engine, "before_cursor_execute", listener)
    try:
        assert due([camera], {camera: CameraCounters(1, MIN_PEOPLE, 0)}) == [camera]  # its first target: read
        assert statements and recording.calibrations == [(camera, False)]
        statements.clear()
        assert due([camera], {camera: CameraCounters(1, MIN_PEOPLE + 1, 0)}) == []  # asked already
        assert statements == []
        assert due([camera]) == [] and len(statements) == 1  # not handed over: the counters are read
    finally:
        event.remove(engine, "before_cursor_execute", listener)


def test_a_solve_the_queue_cannot_take_costs_the_frame_nothing(
    client: TestClient, camera: str, dispatcher: RecordingDispatcher
) -> None:
    def unavailable(camera_id: str, forced: bool) -> None:
        raise DispatchUnavailableError("queue unreachable")

    dispatcher.calibration_requested = unavailable  # type: ignore[method-assign]
    response = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(standing(MIN_PEOPLE)))
    assert response.status_code == 202 and len(dispatcher.frames) == 1


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_frame_result_after_processing(client: TestClient, camera: str, app: FastAPI) -> None:
    people = [{"shoulder": [900, 400], "ankle": [900, 700]}, {"shoulder": [960, 400], "ankle": [960, 700]}]
    accepted = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(people)).json()
    values = CalibrationValues(
        status="ok", person_height_m=1.32, people_used=30, inliers=30, evidence_count=30,
        fx_px=1000.0, fy_px=1000.0, cx_px=960.0, cy_px=540.0, normal=(0.0, -0.8660254, -0.5), rho_m=4.0, noise_px=1.0,
    )  # fmt: skip
    with app.state.session_factory() as session:
        cal = add_calibration(session, camera, values, make_current=True)
        frame = get_frame(session, camera, uuid.UUID(accepted["frame_id"]))
        assert frame is not None
        process_frame(session, frame, get_camera(session, camera), cal)  # type: ignore[arg-type]
        session.commit()
    answer = client.get(accepted["url"])
    assert answer.headers["content-type"] == "application/json"
    frame_out = answer.json()
    assert FrameOut.model_validate(frame_out).result is not None  # the stored result, spliced in, is FrameOut's
    assert frame_out["status"] == "done" and frame_out["calibration_version"] == 1
    result = frame_out["result"]
    assert [p["placed_from"] for p in result["people"]] == ["ankles", "ankles"]
    assert len(result["pairs"]) == 1
    pair = result["pairs"][0]
    assert 0 < pair["distance_m"] < 1.8288 and pair["distance_std_m"] > 0
    assert result["violations"] == [pair]


def test_unknown_camera_and_frame(client: TestClient, camera: str) -> None:
    assert_problem(client.post("/v1/cameras/nope/keypoints", json=frame_body([])), 404, "no camera 'nope'")
    assert_problem(client.get(f"/v1/cameras/{camera}/frames/{uuid.uuid4()}"), 404, "has no frame")
    assert_problem(client.get(f"/v1/cameras/{camera}/frames/not-a-uuid"), 422, "path.frame_id")
    other = client.put("/v1/cameras/cam-2", json={"image_width_px": 640, "image_height_px": 480})
    assert other.status_code == 201
    accepted = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([])).json()
    assert_problem(client.get(f"/v1/cameras/cam-2/frames/{accepted['frame_id']}"), 404, "has no frame")


def _post_raw(client: TestClient, camera: str, content: bytes | str, content_type: str = "application/json"):
    return client.post(f"/v1/cameras/{camera}/keypoints", content=content, headers={"content-type": content_type})


def test_malformed_json_is_400(client: TestClient, camera: str) -> None:
    assert_problem(
        _post_raw(client, camera, b'{"timestamp": "2026-01-01T00:00:00Z", "people": ['), 400, "not valid JSON"
    )


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_numbers_are_422(client: TestClient, camera: str, literal: str) -> None:
    text = '{"timestamp": "2026-01-01T00:00:00Z", "people": [{"shoulder": [LITERAL, 10], "ankle": null}]}'
    text = text.replace("LITERAL", literal)
    problem = assert_problem(_post_raw(client, camera, text), 422, "body.people[0].shoulder[0]", "finite")
    assert problem["errors"][0]["loc"] == ["body", "people", 0, "shoulder", 0]


def _with_keypoint(index: int, value: list[float]) -> list[dict[str, object]]:
    points = coco_person((500, 400), (500, 700))
    points[index] = value
    return [{"keypoints": points}]


@pytest.mark.parametrize(
    ("people", "field", "words"),
    [
        ([{"keypoints": coco_person((500, 400), (500, 700))[:16]}], "body.people[0].keypoints", "exactly 17"),
        ([{"keypoints": [*coco_person((500, 400), (500, 700)), [1, 2, 0.5]]}], "body.people[0].keypoints", "got 18"),
        (_with_keypoint(3, [10, 10]), "body.people[0].keypoints[3]", "required"),
        (_with_keypoint(15, [500, 700, 1.5]), "body.people[0].keypoints[15][2]", "less than or equal to 1"),
        (_with_keypoint(15, [500, 700, -0.1]), "body.people[0].keypoints[15][2]", "greater than or equal to 0"),
        (_with_keypoint(16, [1e6, 700, 0.9]), "body.people[0].keypoints[16]", "far outside"),
        ([{"shoulder": [500, -4000], "ankle": None}], "body.people[0].shoulder", "far outside"),
        ([{"shoulder": [500, 400], "ankle": [500, 700], "knee": [1, 2]}], "body.people[0].knee", "extra"),
        ([{"shoulder": [500, 400], "keypoints": coco_person((500, 400), (500, 700))}], "body.people[0]", "not both"),
        ([{"ankle": [500, 700]}], "body.people[0]", "shoulder"),
        ([{"shoulder": [500]}], "body.people[0].shoulder", ""),
    ],
)
def test_bad_people_name_the_field(client: TestClient, camera: str, people: list, field: str, words: str) -> None:
    problem = assert_problem(client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(people)), 422, field)
    assert any(e["field"].startswith(field) and words.lower() in e["msg"].lower() for e in problem["errors"]), problem


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"timestamp": "2026-01-01T00:00:00", "people": []}, "body.timestamp"),
        ({"timestamp": "yesterday", "people": []}, "body.timestamp"),
        ({"people": []}, "body.timestamp"),
        ({"timestamp": "2026-01-01T00:00:00Z", "people": [], "camera": "x"}, "body.camera"),
        ({"timestamp": "2026-01-01T00:00:00Z", "people": [], "frame_id": "bad id!"}, "body.frame_id"),
        ([1, 2], "body"),
    ],
)
def test_bad_frame_fields(client: TestClient, camera: str, body: object, field: str) -> None:
    problem = assert_problem(client.post(f"/v1/cameras/{camera}/keypoints", json=body), 422, field)
    assert problem["errors"]


def test_unix_timestamps_are_accepted(client: TestClient, camera: str) -> None:
    body = {"timestamp": 1767268800, "people": []}
    accepted = client.post(f"/v1/cameras/{camera}/keypoints", json=body).json()
    assert client.get(accepted["url"]).json()["timestamp"].startswith("2026-01-01T12:00:00")


def test_too_many_people_is_413(client: TestClient, camera: str, app: FastAPI) -> None:
    limit = app.state.settings.max_people_per_frame
    people = [{"shoulder": [500, 400], "ankle": [500, 700]}] * (limit + 1)
    assert_problem(client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(people)), 413, f"at most {limit}")
    assert observation_count(app) == 0


def test_oversize_body_is_413_before_parsing(client: TestClient, camera: str, app: FastAPI) -> None:
    limit = app.state.settings.max_body_bytes
    garbage = b"{" * (limit + 1)  # not JSON: a 413 proves the limit was applied before parsing
    assert_problem(_post_raw(client, camera, garbage), 413, f"limit of {limit} bytes")

    def chunks():
        for _ in range(limit // 1000 + 2):
            yield b" " * 1000

    # Streamed without Content-Length (chunked): counted as it arrives.
    response = client.post(
        f"/v1/cameras/{camera}/keypoints", content=chunks(), headers={"content-type": "application/json"}
    )
    assert_problem(response, 413, "exceeds")


@pytest.mark.parametrize("content_type", ["text/plain", "application/x-www-form-urlencoded", ""])
def test_non_json_body_is_415(client: TestClient, camera: str, content_type: str) -> None:
    body = '{"timestamp": "2026-01-01T00:00:00Z", "people": []}'
    assert_problem(_post_raw(client, camera, body, content_type), 415, "application/json")
    assert client.post(f"/v1/cameras/{camera}/keypoints", content=body,
                       headers={"content-type": "application/json; charset=utf-8"}).status_code == 202  # fmt: skip


def test_pathological_json_is_a_4xx_not_a_500(client: TestClient, camera: str) -> None:
    assert_problem(_post_raw(client, camera, "[" * 50_000), 400)
    assert_problem(_post_raw(client, camera, "9" * 5000), 400)
    assert_problem(_post_raw(client, camera, b"\xff\xfe not utf-8"), 400)
