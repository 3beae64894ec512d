"""API fixtures (a pytest plugin, see tests/conftest.py) and the helpers API tests share: the real app over a real
migrated database, driven in-process with FastAPI's TestClient.

Tests run on SQLite by default; a test parametrised with `backend` ("sqlite", "postgresql") also runs on the
throwaway PostgreSQL cluster (tests.support.databases; skipped without PostgreSQL binaries). The dispatcher
records what the API asks of the workers (tests.support.dispatch); no worker runs.

Every route but the health checks needs an API key: `client` sends the admin key configured in `settings`
(ADMIN_KEY); `anonymous` sends none, and `client_for(token)` gives a client that sends another key.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import cv2
import httpx2 as httpx
import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.app import create_app
from service.domain import CalibrationValues
from service.http.problems import PROBLEM_MEDIA_TYPE
from service.settings import Settings
from tests.support.dispatch import RecordingDispatcher

CAMERA = "cam-1"
ADMIN_KEY = "test-admin-key-0123456789abcdefghijklmnopqrstuvwxyz"
WIDTH_PX, HEIGHT_PX = 1920, 1080
MIN_PEOPLE = 5


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


def solved(evidence: int, fx_px: float = 1000.0) -> CalibrationValues:
    return CalibrationValues(
        status="ok", person_height_m=1.32, people_used=evidence, inliers=evidence - 1, evidence_count=evidence,
        fx_px=fx_px, fy_px=fx_px, cx_px=960.0, cy_px=540.0, normal=(0.0, -0.8660254, -0.5), rho_m=4.0,
        fx_std_px=12.0, fy_std_px=12.0, normal_std_deg=0.5, rho_std_m=0.05, noise_px=1.2,
    )  # fmt: skip


def with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """The JPEG with an EXIF segment whose Orientation tag (1-8) says how a viewer turns its rows."""
    entry = struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0)  # tag, SHORT, one value, the value padded
    tiff = b"MM\x00\x2a" + struct.pack(">I", 8) + struct.pack(">H", 1) + entry + struct.pack(">I", 0)
    app1 = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + jpeg[2:]


def encoded(ext: str, width: int = WIDTH_PX, height: int = HEIGHT_PX) -> bytes:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
    ok, data = cv2.imencode(ext, image)
    assert ok
    return data.tobytes()
