"""The request session's database, as a request sees it (service/http/dependencies.py, service/http/problems.py)."""

from __future__ import annotations

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import create_engine

from service.store.db import make_session_factory


@pytest.mark.both_backends
def test_a_request_that_finds_no_free_pooled_connection_is_told_to_retry(
    app: FastAPI, client: TestClient, camera: str, backend: str
) -> None:
    """The pool's timeout is the database being unavailable for now: 503 with Retry-After, like a database that is
    down, not a 500 (the handler read the driver's error off an exception that has none)."""
    engine = create_engine(app.state.engine.url, pool_size=1, max_overflow=0, pool_timeout=0.2)
    app.state.read_session_factory = make_session_factory(engine, read_only=True)
    held = engine.connect()  # the only connection, taken
    try:
        response = client.get(f"/v1/cameras/{camera}")
        assert response.status_code == 503, response.text
        assert response.headers["content-type"] == "application/problem+json"
        assert response.json()["type"].endswith("database-unavailable")
        assert "TimeoutError" in response.json()["detail"] and "retry-after" in response.headers
    finally:
        held.close()
        engine.dispose()
    assert client.get(f"/v1/cameras/{camera}").status_code == 200  # the connection back: served again
