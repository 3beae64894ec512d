"""A resize holds at once on every API process, and nothing checked against the old size joins the new evidence.

Two apps on one database stand for two API processes, each with its own camera cache: a PUT through one must bind
the other's very next frame (tests/faults/test_resize_across_processes.py does the same with real processes).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select

from service.app import create_app
from service.settings import Settings
from service.store.models import Camera, Frame, FrameImage, Observation
from tests.support.app import ADMIN_KEY, assert_problem, bearer, coco_person, encoded, frame_body
from tests.support.dispatch import RecordingDispatcher

SMALL = {"image_width_px": 640, "image_height_px": 360}


@pytest.fixture
def other_process(settings: Settings) -> Iterator[TestClient]:
    """A second API process on the same database (its own camera cache and frame writer)."""
    with TestClient(create_app(settings, dispatcher=RecordingDispatcher()), headers=bearer(ADMIN_KEY)) as client:
        yield client


def person(x: float) -> dict[str, list[list[float]]]:
    return {"keypoints": coco_person((x, 120.0), (x, 300.0))}


def test_a_resize_elsewhere_binds_this_processes_next_frame(
    app: FastAPI, client: TestClient, camera: str, other_process: TestClient
) -> None:
    # This process reads the 1920x1080 camera and keeps it in memory.
    assert client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([person(1500)])).status_code == 202
    assert app.state.camera_cache.cached(camera).image_width_px == 1920
    # The other process resizes it: the stored people are dropped.
    assert other_process.put(f"/v1/cameras/{camera}", json=SMALL).status_code == 200
    assert app.state.camera_cache.cached(camera).image_width_px == 1920  # still in this process's memory

    # A person at x = 1500 is far outside a 640 px image: refused at once, though this process's memory said 1920.
    refused = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([person(1500)]))
    body = assert_problem(refused, 422, "640x360")
    assert body["errors"][0]["type"] == "coordinate_out_of_image"
    # A person valid in both sizes is stored, judged against the new one: at x = 635 it touches the 640 px border.
    accepted = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([person(300), person(635)]))
    assert accepted.status_code == 202, accepted.text
    with app.state.session_factory() as session:
        people = session.execute(select(Observation.ankle_x_px, Observation.usable)).all()
        evidence = session.get(Camera, camera).usable_evidence_count  # type: ignore[union-attr]
    assert sorted(people) == [(300.0, True), (635.0, False)]
    assert evidence == 1


def test_a_resize_fails_the_frames_still_waiting_with_the_reason(client: TestClient, camera: str) -> None:
    pending = client.post(f"/v1/cameras/{camera}/keypoints", json=frame_body([person(900)])).json()
    image = client.post(
        f"/v1/cameras/{camera}/frames", content=encoded(".jpg"), headers={"content-type": "image/jpeg"}
    ).json()
    assert client.put(f"/v1/cameras/{camera}", json=SMALL).status_code == 200
    for url in (pending["url"], image["url"]):
        frame = client.get(url).json()
        assert frame["status"] == "failed" and "resized to 640x360" in frame["error"], frame
    with client.app.state.session_factory() as session:  # type: ignore[attr-defined]
        assert session.scalars(select(FrameImage.frame_id)).all() == []  # the waiting image went too
        assert {f.status for f in session.scalars(select(Frame))} == {"failed"}
