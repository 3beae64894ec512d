"""Static spots: a "person" found unmoved frame after frame (a mannequin) gives no evidence and no violation."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
import redis
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from bench.towncentre import load_annotations
from service.cameras.repository import upsert_camera
from service.cameras.static_spots import FORGET_AFTER_S, match_spots, observe, static_spots
from service.frames.keypoints import STATIC_REASON
from service.pose.merge import iou_matrix
from service.queue import RedisDispatcher
from service.settings import get_settings
from service.store import Frame, Observation
from tests.support.jobs import run_jobs, store_image
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir

START = datetime(2026, 1, 1, tzinfo=UTC)
MANNEQUIN = (100.0, 200.0, 160.0, 380.0)


def test_boxes_match_the_spot_they_overlap_most_once_each() -> None:
    spots = [MANNEQUIN, (500.0, 200.0, 560.0, 380.0)]
    jitter = (102.0, 201.0, 161.0, 383.0)
    walked = (130.0, 200.0, 190.0, 380.0)  # half a body width further: another place
    assert match_spots([jitter, walked, (501.0, 199.0, 560.0, 381.0)], spots) == [0, None, 1]
    assert match_spots([jitter, jitter], spots) == [0, None]  # one spot, one box
    assert match_spots([], spots) == [] and match_spots([jitter], []) == [None]


def test_a_spot_is_static_after_the_setting_and_forgotten_when_unseen(sessions: sessionmaker[Session]) -> None:
    with sessions() as session, session.begin():
        upsert_camera(session, "shop", image_width_px=640, image_height_px=480, person_height_m=1.32)
        verdicts = [
            observe(
                session, "shop", START + timedelta(seconds=t), [MANNEQUIN, (10.0 + 20 * t, 50, 60 + 20 * t, 200)], 30
            )
            for t in range(0, 50, 5)
        ]
        # The mannequin: static once seen over 30 s; the walker opens a new spot in every frame, never static.
        assert [v[0] for v in verdicts] == [False] * 6 + [True] * 4
        assert not any(v[1] for v in verdicts)
        assert [(s.left_px, s.sightings) for s in static_spots(session, "shop", 30)] == [(100.0, 10)]
        # A minute unseen: forgotten, and the walker's spots with it; seen again it starts over.
        later = START + timedelta(seconds=45 + FORGET_AFTER_S + 1)
        assert observe(session, "shop", later, [MANNEQUIN, None], 30) == [False, False]
        assert static_spots(session, "shop", 30) == []


@pytest.fixture
def short_static(monkeypatch: pytest.MonkeyPatch) -> Iterator[float]:
    monkeypatch.setenv("POSEMETRY_STATIC_AFTER_S", "3")
    get_settings.cache_clear()
    yield 3.0
    get_settings.cache_clear()


def test_town_centre_mannequins_are_static_and_the_pedestrians_are_not(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    short_static: float,
) -> None:
    """The clip's 5 s at 25 fps through the real pose job, with static spots after 3 s: the shop-window mannequins
    (in every frame, unmoved) become static spots; no annotated pedestrian of the last frame stands on one."""
    require_dir(model_dir_path(), "pose model")
    frames = sorted((require_dir(TOWN_CENTRE, "Town Centre data") / "frames").glob("clip_*.jpg"))
    for path in frames:
        at = START + timedelta(seconds=int(path.stem.split("_")[1]) / 25)
        redis_dispatcher.image_stored("town", store_image(sessions, path.read_bytes(), timestamp=at))
    run_jobs(connection)
    with sessions() as session:
        spots = static_spots(session, "town", short_static)
        last = session.query(Frame).order_by(Frame.timestamp.desc()).first()
        assert last is not None
        people = session.query(Observation).filter_by(frame_id=last.id).all()
    boxes = np.array([(s.left_px, s.top_px, s.right_px, s.bottom_px) for s in spots]).reshape(-1, 4)
    assert len(spots) >= 1
    last_index = int(frames[-1].stem.split("_")[1])
    walkers = load_annotations(TOWN_CENTRE / "TownCentre-groundtruth.top", {last_index})[last_index]
    truth = np.array([a.body_xyxy for a in walkers if a.body_xyxy is not None])
    assert iou_matrix(boxes, truth).max() < 0.3  # no spot is a real pedestrian
    static = [p for p in people if p.unusable_reason == STATIC_REASON]
    assert len(static) >= 1 and not any(p.usable for p in static)
    assert all(iou_matrix(np.array([p.box_px]), boxes).max() >= 0.8 for p in static)


def test_the_camera_lists_its_static_spots(app: FastAPI, client: TestClient) -> None:
    assert client.put("/v1/cameras/shop", json={"image_width_px": 640, "image_height_px": 480}).status_code == 201
    with app.state.session_factory() as session, session.begin():
        for t in range(0, 901, 50):  # the default static_after_s is 900 s; seen at least once a minute
            observe(session, "shop", START + timedelta(seconds=t), [MANNEQUIN], 900)
        observe(session, "shop", START + timedelta(seconds=950), [(300.0, 100.0, 340.0, 200.0)], 900)
    answer = client.get("/v1/cameras/shop/static-spots")
    assert answer.status_code == 200
    assert answer.json() == {
        "static_after_s": 900.0,
        "items": [
            {
                "box_px": list(MANNEQUIN),
                "first_seen": "2026-01-01T00:00:00Z",
                "last_seen": "2026-01-01T00:15:00Z",
                "sightings": 19,
            }
        ],
    }
    assert client.get("/v1/cameras/nowhere/static-spots").status_code == 404
