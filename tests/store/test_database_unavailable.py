"""A database that cannot be used right now is a 503 problem with Retry-After, never a 500; a database error that
is a bug stays a 500. Here the real SQLite file is write-locked by another connection past the busy timeout, and
on PostgreSQL the server is out of reach (the process tests stop a real one: tests/faults)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import exc as sa_exc

from service.app import create_app
from service.settings import Settings
from service.store.db import is_database_unavailable
from tests.support.app import ADMIN_KEY, CAMERA, assert_problem, bearer, frame_body, standing
from tests.support.dispatch import RecordingDispatcher


def test_a_write_locked_sqlite_database_is_a_503_and_the_retry_stores_the_frame_once(
    settings: Settings, dispatcher: RecordingDispatcher
) -> None:
    app = create_app(settings.model_copy(update={"database_busy_timeout_s": 0.2}), dispatcher=dispatcher)
    body = frame_body(standing(3), frame_id="f-locked")
    with TestClient(app, headers=bearer(ADMIN_KEY)) as client:
        assert client.put(f"/v1/cameras/{CAMERA}", json={"image_width_px": 1920, "image_height_px": 1080}).is_success
        path = Path(settings.database_url.removeprefix("sqlite:///"))
        blocker = sqlite3.connect(path, isolation_level=None)
        try:
            blocker.execute("BEGIN IMMEDIATE")
            refused = client.post(f"/v1/cameras/{CAMERA}/keypoints", json=body)
            problem = assert_problem(refused, 503, "database is unavailable")
            assert problem["type"].endswith("/database-unavailable") and refused.headers["retry-after"] == "5"
            assert client.get(f"/v1/cameras/{CAMERA}").status_code == 200  # reads go on meanwhile
        finally:
            blocker.execute("ROLLBACK")
            blocker.close()
        accepted = client.post(f"/v1/cameras/{CAMERA}/keypoints", json=body)
        assert accepted.status_code == 202, accepted.text  # the refused attempt stored nothing
        assert client.post(f"/v1/cameras/{CAMERA}/keypoints", json=body).status_code == 200


def test_an_unreachable_postgresql_is_a_503_on_every_route_that_needs_it(settings: Settings) -> None:
    # A server that does not listen there: connecting fails at once (as when PostgreSQL is stopped).
    url = "postgresql+psycopg://nobody@/posemetry?host=/nonexistent-socket-dir&port=5999"
    app = create_app(settings.model_copy(update={"database_url": url}), dispatcher=RecordingDispatcher())
    with TestClient(app, headers=bearer(ADMIN_KEY)) as client:
        for method, path, json in [
            ("GET", "/v1/cameras", None),
            ("PUT", f"/v1/cameras/{CAMERA}", {"image_width_px": 1920, "image_height_px": 1080}),
            ("POST", f"/v1/cameras/{CAMERA}/keypoints", frame_body(standing(2))),
        ]:
            response = client.request(method, path, json=json)
            assert assert_problem(response, 503)["type"].endswith("/database-unavailable"), (method, path)
        ready = client.get("/readyz")
        assert_problem(ready, 503, "database")


@pytest.mark.parametrize(
    ("error", "unavailable"),
    [
        (sa_exc.OperationalError("SELECT 1", None, Exception("server closed the connection")), True),
        (sa_exc.InterfaceError("SELECT 1", None, Exception("connection already closed")), True),
        (sa_exc.TimeoutError("QueuePool limit reached"), True),
        (sa_exc.IntegrityError("INSERT", None, Exception("duplicate key")), False),
        (sa_exc.ProgrammingError("SELECT", None, Exception("syntax error")), False),
    ],
)
def test_which_database_errors_mean_unavailable(error: Exception, unavailable: bool) -> None:
    assert is_database_unavailable(error) is unavailable
