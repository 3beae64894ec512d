"""A keypoint camera posting a frame every 2 s with its tracker's ids, end to end: frames over HTTP, the calibration
job on a real RQ worker and Redis, the result over HTTP. Motion cannot link sightings 2 s apart and keypoints carry
no appearance, so without the ids every sighting is an individual; with them, every person is one."""

from __future__ import annotations

from typing import Any

import numpy as np
import redis
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from bench.simulate import SceneConfig, draw_scene
from service.app import create_app
from service.geometry.tracks import MAX_GAP_S
from service.queue import RedisDispatcher
from service.settings import get_settings
from tests.support.app import ADMIN_KEY, bearer, frame_body
from tests.support.jobs import run_jobs

SPACING_S = 2.0
SIGHTINGS = 4


def _post_walkers(client: TestClient, camera: str, *, with_ids: bool) -> int:
    """Frame k holds every walker's k-th sighting, frames SPACING_S apart; returns how many walkers there are."""
    scene = draw_scene(
        SceneConfig.surveillance(
            n_people=100, observations_per_person=SIGHTINGS, height_mean_m=1.32, height_std_m=0.08
        ),
        np.random.default_rng(11),
    )
    body = {"image_width_px": scene.image_size[0], "image_height_px": scene.image_size[1], "person_height_m": 1.32}
    assert client.put(f"/v1/cameras/{camera}", json=body).status_code in (200, 201)
    sighting = np.zeros(len(scene.tracks), dtype=int)
    for label in np.unique(scene.tracks):
        rows = np.flatnonzero(scene.tracks == label)
        sighting[rows] = np.arange(len(rows))
    for k in range(SIGHTINGS):
        people: list[dict[str, Any]] = []
        for i in np.flatnonzero(sighting == k):
            person: dict[str, Any] = {"shoulder": scene.tops_px[i].tolist(), "ankle": scene.bottoms_px[i].tolist()}
            if with_ids:
                person["track_id"] = f"walker-{scene.tracks[i]}"
            people.append(person)
        timestamp = f"2026-01-01T12:00:{SPACING_S * k:02.0f}Z"
        response = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body(people, timestamp=timestamp))
        assert response.status_code == 202, response.text
    assert client.post(f"/v1/cameras/{camera}/calibration").status_code == 202
    return len(np.unique(scene.tracks))


def test_a_keypoint_camera_posting_every_two_seconds_gets_its_individuals_from_the_track_ids(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> None:
    assert SPACING_S > MAX_GAP_S
    app = create_app(get_settings(), dispatcher=redis_dispatcher)
    with TestClient(app, headers=bearer(ADMIN_KEY)) as client:
        walkers = _post_walkers(client, "tracked", with_ids=True)
        assert _post_walkers(client, "untracked", with_ids=False) == walkers
        run_jobs(connection)
        tracked = client.get("/v1/cameras/tracked/calibration").json()
        untracked = client.get("/v1/cameras/untracked/calibration").json()
    assert tracked["status"] == untracked["status"] == "calibrated", (tracked, untracked)
    # The same sightings, so about as many inliers; the ids make them a quarter as many individuals.
    assert tracked["inliers"] > 2 * walkers and untracked["inliers"] > 2 * walkers
    assert untracked["camera_model"]["individuals"] == untracked["inliers"]
    assert 0.8 * walkers <= tracked["camera_model"]["individuals"] <= walkers
