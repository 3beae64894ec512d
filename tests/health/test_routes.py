"""Health and readiness, and problem documents for unknown routes and methods."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.support.app import assert_problem
from tests.support.dispatch import RecordingDispatcher


def test_health_and_readiness(client: TestClient, dispatcher: RecordingDispatcher) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["checks"] == {"database": "ok", "queue": "ok"}
    dispatcher.fail = True
    problem = assert_problem(client.get("/readyz"), 503, "queue unreachable")
    assert problem["checks"]["database"] == "ok"


def test_unknown_routes_and_methods_are_problems(client: TestClient) -> None:
    assert_problem(client.get("/v2/cameras"), 404, "/v2/cameras")
    refused = client.patch("/v1/cameras/x", json={})
    assert_problem(refused, 405, "PATCH", "allowed: GET, PUT, DELETE")
    assert refused.headers["allow"] == "GET, PUT, DELETE"  # three routes serve the path, not just the first
    # A path no route takes is a 404 whatever the method and body: the body guard does not read it.
    assert_problem(client.post("/v1/nothing", content=b"x" * 10, headers={"Content-Type": "text/plain"}), 404)
