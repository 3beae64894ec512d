"""Static spots for keypoint frames: a mannequin posted by a client's own pose model, through the real measuring job
(real Redis, a real migrated database, a real RQ worker)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
import redis
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from service.cameras.static_rule import KEYPOINT_SAMPLE_S, centre_box
from service.cameras.static_spots import static_spots
from service.frames.ingest import add_keypoint_frame
from service.frames.keypoints import STATIC_REASON, person_from_centres
from service.pose.merge import iou_matrix
from service.queue import CALIBRATION_QUEUE, RedisDispatcher
from service.settings import get_settings
from service.store.models import Camera, Frame, Observation, StaticSpot
from tests.support.jobs import IMAGE_SIZE, frame_statuses, run_jobs, simulated_camera, store_frames
from tests.support.jobs import Camera as SimulatedCamera

STATIC_AFTER_S = 60.0
START = datetime(2026, 1, 1, 1, tzinfo=UTC)
SPACING_S = KEYPOINT_SAMPLE_S  # every frame is a sample: the spot's story is told in a minute of frame time


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request: pytest.FixtureRequest) -> str:
    """The conditional updates that take a static person out of the evidence behave alike on both databases."""
    return str(request.param)


@pytest.fixture
def short_static(monkeypatch: pytest.MonkeyPatch) -> Iterator[float]:
    monkeypatch.setenv("POSEMETRY_STATIC_AFTER_S", str(STATIC_AFTER_S))
    get_settings.cache_clear()
    yield STATIC_AFTER_S
    get_settings.cache_clear()


def test_a_still_body_keeps_its_box_and_a_walker_does_not() -> None:
    rng = np.random.default_rng(0)
    shoulder, ankle = np.array([400.0, 300.0]), np.array([404.0, 420.0])
    # A still body's centres jitter by 1 % of its 120 px segment per coordinate; each sighting is matched against
    # the spot's first box.
    jitter = rng.normal(0, 1.2, (50, 2, 2))
    still = [centre_box(tuple(shoulder + a), tuple(ankle + b)) for a, b in jitter]
    assert iou_matrix(np.array(still), np.array(still[:1])).min() > 0.8
    # A walker a second later: a stride (~0.7 m, 0.5 of a 1.32 m segment) further along the street.
    walked = centre_box(tuple(shoulder + [60.0, 0.0]), tuple(ankle + [60.0, 0.0]))
    assert iou_matrix(np.array([walked]), np.array(still[:1]))[0, 0] < 0.5


def _post(sessions: sessionmaker[Session], at: datetime, people: list[tuple[np.ndarray, np.ndarray]]) -> None:
    persons = [person_from_centres(tuple(top), tuple(bottom), IMAGE_SIZE) for top, bottom in people]
    with sessions() as session, session.begin():
        add_keypoint_frame(session, "cam-1", timestamp=at, people=persons)


def _results(sessions: sessionmaker[Session]) -> list[dict]:
    with sessions() as session:
        rows = session.scalars(select(Frame).where(Frame.timestamp >= START).order_by(Frame.timestamp)).all()
        return [json.loads(row.result) if isinstance(row.result, str) else row.result for row in rows]


def _calibrated(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis
) -> SimulatedCamera:
    """cam-1 calibrated from 40 frames of 10 people (graded above unreliable, so it raises violations)."""
    camera = simulated_camera(sessions, people=800)
    store_frames(sessions, camera, 40)
    redis_dispatcher.request(CALIBRATION_QUEUE, camera.camera_id)
    run_jobs(connection)
    assert frame_statuses(sessions) == {"done": 40}
    return camera


def test_a_mannequin_in_keypoint_frames_turns_static_gives_no_evidence_and_no_violation(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis, short_static: float
) -> None:
    camera = _calibrated(sessions, redis_dispatcher, connection)

    mannequin = (camera.scene.tops_px[-1], camera.scene.bottoms_px[-1])
    length = float(np.linalg.norm(mannequin[0] - mannequin[1]))
    beside = np.array([0.3 * length, 0.0])  # a shopper stopping half a metre from it

    def frame(k: int, shopper: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
        tops, bottoms = camera.frame_people(4)
        people = [mannequin, *zip(tops, bottoms, strict=True)]
        if shopper:
            people.append((mannequin[0] + shopper * beside, mannequin[1] + shopper * beside))
        return people

    # The first minute: the mannequin is seen (a sighting every sample), a shopper stops beside it once.
    for k in range(7):
        _post(sessions, START + timedelta(seconds=SPACING_S * k), frame(k, shopper=1 if k == 1 else 0))
    redis_dispatcher.measure_requested(["cam-1"])
    run_jobs(connection)
    # Then it has stood for static_after_s: another shopper beside it in the last two frames.
    for k in range(7, 13):
        _post(sessions, START + timedelta(seconds=SPACING_S * k), frame(k, shopper=-1 if k >= 11 else 0))
    redis_dispatcher.measure_requested(["cam-1"])
    run_jobs(connection)
    assert frame_statuses(sessions) == {"done": 40 + 13}

    results = _results(sessions)
    static = [result["people"][0]["static"] for result in results]
    assert static == [False] * 7 + [True] * 6  # the chunk after the spot turned static on
    assert not any(person["static"] for result in results for person in result["people"][1:])
    with_mannequin = [[v for v in result["violations"] if 0 in (v["i"], v["j"])] for result in results]
    assert results[1]["calibration_grade"] != "unreliable"  # an unreliable camera raises no violation at all
    assert with_mannequin[1], "before it is static, the shopper beside it is a violation"
    assert not any(with_mannequin[7:]), "a static spot raises no violation"
    assert [len(result["people"]) for result in results[11:]] == [6, 6]

    with sessions() as session:
        mannequin_rows = session.scalars(
            select(Observation)
            .join(Frame, Frame.id == Observation.frame_id)
            .where(Frame.timestamp >= START, Observation.person_index == 0)
            .order_by(Frame.timestamp)
        ).all()
        assert [row.unusable_reason == STATIC_REASON for row in mannequin_rows] == [False] * 7 + [True] * 6
        assert [row.static for row in mannequin_rows] == [False] * 7 + [True] * 6  # measured again as static
        assert not any(row.usable for row in mannequin_rows[7:])
        usable = session.scalar(select(func.count()).where(Observation.camera_id == "cam-1", Observation.usable))
        stored = session.get(Camera, "cam-1")
        assert stored is not None and stored.usable_evidence_count == usable  # the counter follows
        spots = static_spots(session, "cam-1", short_static)
        assert len(spots) == 1 and spots[0].sightings == 13
        box = np.array([[spots[0].left_px, spots[0].top_px, spots[0].right_px, spots[0].bottom_px]])
        assert iou_matrix(box, np.array([centre_box(tuple(mannequin[0]), tuple(mannequin[1]))]))[0, 0] > 0.99
        # The walkers' spots are forgotten a minute after their sighting: the table stays small.
        assert session.scalar(select(func.count()).select_from(StaticSpot)) <= 1 + 5 * (60 / SPACING_S + 1)


def test_only_one_keypoint_frame_per_sample_interval_is_a_sighting(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis, short_static: float
) -> None:
    camera = _calibrated(sessions, redis_dispatcher, connection)
    mannequin = (camera.scene.tops_px[-1], camera.scene.bottoms_px[-1])
    for k in range(25):  # 5 frames a second for 5 s: one sample
        _post(sessions, START + timedelta(seconds=0.2 * k), [mannequin])
    redis_dispatcher.measure_requested(["cam-1"])
    run_jobs(connection)
    with sessions() as session:
        spots = session.scalars(select(StaticSpot).where(StaticSpot.camera_id == "cam-1")).all()
    boxes = np.array([(s.left_px, s.top_px, s.right_px, s.bottom_px) for s in spots])
    at_mannequin = iou_matrix(boxes, np.array([centre_box(tuple(mannequin[0]), tuple(mannequin[1]))]))[:, 0] > 0.8
    assert [s.sightings for s, here in zip(spots, at_mannequin, strict=True) if here] == [1]
