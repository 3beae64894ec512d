"""API fixtures: the real app over a real migrated database, driven in-process with FastAPI's TestClient.

Tests run on SQLite by default; a test parametrised with `backend` ("sqlite", "postgresql") also runs on the
throwaway PostgreSQL cluster of the store tests (skipped without PostgreSQL binaries).

Every route but the health checks needs an API key: `client` sends the admin key configured in `settings`
(ADMIN_KEY); `anonymous` sends none, and `client_for(token)` gives a client that sends another key.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx2 as httpx
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.app import create_app
from service.dispatch import RecordingDispatcher
from service.problems import PROBLEM_MEDIA_TYPE
from service.settings import Settings
from tests.store.conftest import migrated_url, postgres_cluster, postgres_template, sqlite_template

__all__ = ["migrated_url", "postgres_cluster", "postgres_template", "sqlite_template"]

CAMERA = "cam-1"
ADMIN_KEY = "test-admin-key-0123456789abcdefghijklmnopqrstuvwxyz"
WIDTH_PX, HEIGHT_PX = 1920, 1080
MIN_PEOPLE = 5


@pytest.fixture
def backend() -> str:
    """SQLite unless a test parametrises `backend` itself."""
    return "sqlite"


@pytest.fixture
def dispatcher() -> RecordingDispatcher:
    return RecordingDispatcher()


@pytest.fixture
def settings(migrated_url: str, tmp_path: Path) -> Settings:
    return Settings(
        database_url=migrated_url,
        data_dir=tmp_path,
        max_people_per_frame=50,
        max_body_bytes=200_000,
        calibration_min_people=MIN_PEOPLE,
        calibration_growth_factor=2.0,
        admin_key=ADMIN_KEY,
    )


@pytest.fixture
def app(settings: Settings, dispatcher: RecordingDispatcher) -> FastAPI:
    return create_app(settings, dispatcher=dispatcher)


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture
def client(app: FastAPI) -> Iterator[TestClient]:
    """The app as an admin sees it (the configured admin key on every request)."""
    with TestClient(app, headers=bearer(ADMIN_KEY)) as test_client:
        yield test_client


@pytest.fixture
def anonymous(app: FastAPI) -> Iterator[TestClient]:
    """The app as a caller without a key sees it."""
    with TestClient(app) as test_client:
        yield test_client


@pytest.fixture
def camera(client: TestClient) -> str:
    response = client.put(f"/v1/cameras/{CAMERA}", json={"image_width_px": WIDTH_PX, "image_height_px": HEIGHT_PX})
    assert response.status_code == 201, response.text
    return CAMERA


def coco_person(shoulder: tuple[float, float], ankle: tuple[float, float], score: float = 0.9) -> list[list[float]]:
    """17 COCO keypoints whose shoulder and ankle centres are exactly `shoulder` and `ankle`."""
    (sx, sy), (ax, ay) = shoulder, ankle
    points = [[sx + (ax - sx) * t, sy + (ay - sy) * t, score] for t in [-0.2] * 5 + [0.0] * 2 + [0.3] * 4]
    points[5] = [sx - 15, sy, score]
    points[6] = [sx + 15, sy, score]
    points += [[sx + (ax - sx) * 0.5, sy + (ay - sy) * 0.5, score]] * 4
    points += [[ax - 8, ay, score], [ax + 8, ay, score]]
    assert len(points) == 17
    return points


def frame_body(people: list[dict[str, Any]], frame_id: str | None = None, timestamp: str = "2026-01-01T12:00:00Z"):
    body: dict[str, Any] = {"timestamp": timestamp, "people": people}
    if frame_id is not None:
        body["frame_id"] = frame_id
    return body


def standing(n: int, x0: float = 300.0) -> list[dict[str, Any]]:
    """n upright, fully visible COCO people spread across the image."""
    return [{"keypoints": coco_person((x0 + 120 * i, 400.0), (x0 + 120 * i, 700.0))} for i in range(n)]


def assert_problem(response: httpx.Response, status: int, *fragments: str) -> dict[str, Any]:
    """A problem+json answer with this status whose detail mentions every fragment (case-insensitive)."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE), response.headers
    body = response.json()
    assert body["status"] == status
    assert body["type"].startswith("https://")
    assert body["title"]
    for fragment in fragments:
        assert fragment.lower() in body["detail"].lower(), body["detail"]
    return body


@pytest.fixture
def client_for(app: FastAPI) -> Iterator[Callable[[str], TestClient]]:
    """Clients of the same app that send the given key (closed at the end of the test)."""
    with ExitStack() as stack:
        yield lambda token: stack.enter_context(TestClient(app, headers=bearer(token)))
