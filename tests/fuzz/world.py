"""A small, real world for the fuzzer to wander in: without it nearly every generated request would name a camera,
frame or subscription that does not exist, and only the 404 paths would ever be tested.

`seed_template` builds it once per session, through the API itself (plus the repository for what only workers
write: a calibration and a measured frame): a calibrated camera that keeps images, with a measured keypoint frame
(with a violation), an image frame, a webhook subscription with a delivery, a second camera, and a key limited to
the first camera. Each test then opens its own copy of that database (`open_world`), so an operation that
deletes or changes things (DELETE a camera, PUT a new image size) cannot spoil the next operation's test.
"""

from __future__ import annotations

import json
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import httpx2 as httpx
import numpy as np
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.app import create_app
from service.calibration.repository import add_calibration
from service.cameras.repository import get_camera
from service.domain import CalibrationValues
from service.frames.repository import get_frame
from service.settings import Settings
from service.webhooks import repository as webhook_store
from tests.support.app import ADMIN_KEY, bearer
from tests.support.dispatch import RecordingDispatcher
from tests.support.measure import process_frame

CAMERA = "lobby-1"
OTHER_CAMERA = "yard-2"
WIDTH_PX, HEIGHT_PX = 640, 480
# Two people side by side (a violation under the calibration below) and one further back.
PEOPLE = [
    {"shoulder": [300, 200], "ankle": [300, 400]},
    {"shoulder": [330, 200], "ankle": [330, 400]},
    {"shoulder": [560, 150], "ankle": [560, 290]},
]
CALIBRATION = CalibrationValues(
    status="ok", person_height_m=1.32, people_used=30, inliers=30, evidence_count=30,
    fx_px=500.0, fy_px=500.0, cx_px=320.0, cy_px=240.0, normal=(0.0, -0.8660254, -0.5), rho_m=4.0, noise_px=1.0,
)  # fmt: skip
# The webhook receiver: loopback, which the fuzz settings allow (nothing listens, and nothing is sent: the
# dispatcher only records).
WEBHOOK_URL = "http://127.0.0.1:9/posemetry"
ALLOWED_NETWORKS = "127.0.0.0/8"


@dataclass(frozen=True)
class WorldTemplate:
    database: Path
    scoped_token: str
    """A key limited to CAMERA."""
    known_values: dict[str, tuple[str, ...]]
    """Real values per path parameter name (camera_id, frame_id, subscription_id, delivery_id, key_id)."""
    image: bytes
    """A JPEG of the cameras' size."""


@dataclass(frozen=True)
class FuzzWorld:
    app: FastAPI
    template: WorldTemplate


def settings_for(database: Path) -> Settings:
    return Settings(
        database_url=f"sqlite:///{database}",
        data_dir=database.parent,
        admin_key=ADMIN_KEY,
        webhook_allowed_networks=ALLOWED_NETWORKS,  # type: ignore[arg-type]
    )


def jpeg(width: int = WIDTH_PX, height: int = HEIGHT_PX) -> bytes:
    image = np.random.default_rng(0).integers(0, 255, (height, width, 3), dtype=np.uint8)
    ok, data = cv2.imencode(".jpg", image)
    assert ok
    return data.tobytes()


def _ok(response: httpx.Response, status: int = 201) -> dict[str, Any]:
    assert response.status_code == status, response.text
    return response.json()  # type: ignore[no-any-return]


def seed_template(database: Path) -> WorldTemplate:
    """Seed a migrated database (a copy of the store fixtures' template) with the world."""
    app = create_app(settings_for(database), dispatcher=RecordingDispatcher())
    picture = jpeg()
    with TestClient(app, headers=bearer(ADMIN_KEY)) as client:
        camera = {"image_width_px": WIDTH_PX, "image_height_px": HEIGHT_PX, "keep_images": True}
        _ok(client.put(f"/v1/cameras/{CAMERA}", json=camera))
        _ok(client.put(f"/v1/cameras/{OTHER_CAMERA}", json=camera))
        frame_body = {"timestamp": "2026-01-01T12:00:00Z", "frame_id": "seed-1", "people": PEOPLE}
        measured = _ok(client.post(f"/v1/cameras/{CAMERA}/keypoints", json=frame_body), 202)
        image = _ok(
            client.post(
                f"/v1/cameras/{CAMERA}/frames?frame_id=seed-2", content=picture, headers={"Content-Type": "image/jpeg"}
            ),
            202,
        )
        subscription = _ok(client.post("/v1/webhooks", json={"url": WEBHOOK_URL, "camera_ids": [CAMERA]}))
        scoped = _ok(client.post("/v1/keys", json={"name": "fuzz: one camera", "cameras": [CAMERA]}))
    with app.state.session_factory() as session:
        calibration = add_calibration(session, CAMERA, CALIBRATION, make_current=True)
        frame = get_frame(session, CAMERA, uuid.UUID(measured["frame_id"]))
        outcome = process_frame(session, frame, get_camera(session, CAMERA), calibration)  # type: ignore[arg-type]
        assert outcome.violations, "the seeded frame should hold a violation, for the heat map"
        subscriptions = [webhook_store.get_subscription(session, uuid.UUID(subscription["id"]))]
        deliveries = webhook_store.raise_event(
            session,
            event_type="violation.detected",
            camera_id=CAMERA,
            body=json.dumps({"type": "violation.detected", "data": {"camera_id": CAMERA}}),
            subscriptions=subscriptions,  # type: ignore[arg-type]
        )
        session.commit()
    app.state.engine.dispose()
    return WorldTemplate(
        database=database,
        scoped_token=scoped["token"],
        image=picture,
        # Repeats weight the draw: mostly the calibrated camera and its measured frame.
        known_values={
            "camera_id": (CAMERA, CAMERA, CAMERA, OTHER_CAMERA),
            "frame_id": (measured["frame_id"], measured["frame_id"], image["frame_id"]),
            "subscription_id": (subscription["id"],),
            "delivery_id": tuple(str(d) for d in deliveries),
            "key_id": (scoped["id"],),
        },
    )


def open_world(template: WorldTemplate, directory: Path) -> FuzzWorld:
    """A fresh copy of the seeded world, served by a new app."""
    database = directory / "world.sqlite3"
    shutil.copyfile(template.database, database)
    return FuzzWorld(app=create_app(settings_for(database), dispatcher=RecordingDispatcher()), template=template)
