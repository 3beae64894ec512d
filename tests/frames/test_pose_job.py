"""The pose job on real frames with the real ONNX models: people stored once, images dropped unless kept."""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
import redis
from rq import Queue
from sqlalchemy.orm import Session, sessionmaker

from service.calibration.repository import current_calibration
from service.cameras.repository import get_camera
from service.domain import DONE, FAILED, GONE, SKIPPED
from service.frames.repository import frame_image
from service.queue import CALIBRATION_QUEUE, FRAMES_QUEUE, POSE_QUEUE, RedisDispatcher
from service.settings import get_settings
from service.store import Frame, Observation
from tests.support.jobs import run_jobs, store_image
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir
from workers import jobs
from workers.main import requeue_pending

CAMERA = "town"


@pytest.fixture(scope="module")
def town_jpeg() -> bytes:
    require_dir(model_dir_path(), "pose model")
    return (require_dir(TOWN_CENTRE, "Town Centre data") / "frames" / "clip_000000.jpg").read_bytes()


def test_pose_job_stores_people_once_and_drops_the_image(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis, town_jpeg: bytes
) -> None:
    frame_id = store_image(sessions, town_jpeg)
    redis_dispatcher.image_stored(CAMERA, frame_id)
    redis_dispatcher.image_stored(CAMERA, frame_id)
    assert Queue(POSE_QUEUE, connection=connection).get_job_ids() == [f"pose-{frame_id}"]  # queued once
    assert jobs.detect_people(str(frame_id)) == DONE
    assert jobs.detect_people(str(frame_id)) == SKIPPED  # a duplicate run stores nothing more
    with sessions() as session:
        frame = session.get(Frame, frame_id)
        assert frame is not None and frame.status == "pending" and frame.pose_model.startswith("rtmdet-nano")
        people = session.query(Observation).filter_by(frame_id=frame_id).order_by(Observation.person_index).all()
        assert frame.people == len(people) >= 10  # about 13-17 pedestrians in this frame
        usable = [p for p in people if p.usable]
        # 5 measured with Thunder since only standing people with trusted ankles are evidence (8 before: one with
        # an unseen knee, one cut by the frame's bottom edge and one repeated detection no longer count).
        assert len(usable) >= 5
        for person in people:
            left, top, right, bottom = person.box_px
            assert 0 <= left < right <= 1920 and 0 <= top < bottom <= 1080
            assert 0.3 <= person.detection_score <= 1.0
            assert person.keypoints is not None and len(person.keypoints) == 17
        for person in usable:  # upright: ankles below shoulders, inside the box (with margin)
            assert person.ankle_y_px > person.shoulder_y_px
            assert person.box_px[1] - 20 <= person.shoulder_y_px and person.ankle_y_px <= person.box_px[3] + 20
        camera = get_camera(session, CAMERA)
        assert camera is not None and camera.usable_evidence_count == len(usable)
        assert frame_image(session, frame_id) is None  # privacy: the picture is gone once its people are stored
    # The pose job measured the frame itself (it waits, uncalibrated); its repeat asked for a frames job.
    assert Queue(FRAMES_QUEUE, connection=connection).count == 1


def test_kept_images_stay(sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, town_jpeg: bytes) -> None:
    frame_id = store_image(sessions, town_jpeg, keep_images=True)
    assert jobs.detect_people(str(frame_id)) == DONE
    with sessions() as session:
        assert frame_image(session, frame_id) is not None


def test_missing_models_fail_the_frame_with_the_fix(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    town_jpeg: bytes,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    frame_id = store_image(sessions, town_jpeg)
    monkeypatch.setenv("POSEMETRY_MODEL_DIR", str(tmp_path / "no-models"))
    get_settings.cache_clear()
    assert jobs.detect_people(str(frame_id)) == FAILED
    with sessions() as session:
        frame = session.get(Frame, frame_id)
        assert frame is not None and frame.status == "failed"
        assert "rtmdet_nano_person_320.onnx" in frame.error and "posemetry models fetch" in frame.error


def test_an_image_corrupted_in_storage_fails_only_its_frame(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, town_jpeg: bytes
) -> None:
    good = store_image(sessions, town_jpeg)
    with sessions() as session, session.begin():
        image = frame_image(session, good)
        assert image is not None
        image.data = town_jpeg[:4] + b"\x00" * 500 + b"\xff\xd9"  # what a damaged disk page might leave
    assert jobs.detect_people(str(good)) == FAILED
    assert _status(sessions, good) == "failed"
    assert jobs.detect_people(str(uuid.uuid4())) == GONE


def _status(sessions: sessionmaker[Session], frame_id: uuid.UUID) -> str:
    with sessions() as session:
        frame = session.get(Frame, frame_id)
        assert frame is not None
        return frame.status


def test_worker_start_requeues_images_still_detecting(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis, town_jpeg: bytes
) -> None:
    frame_id = store_image(sessions, town_jpeg)  # stored while Redis was "down": never dispatched
    requeued = requeue_pending(get_settings(), redis_dispatcher)
    assert requeued.images == 1
    assert requeue_pending(get_settings(), redis_dispatcher).images == 0
    run_jobs(connection)
    assert _status(sessions, frame_id) == "pending"  # people found; waiting for a calibration


def test_town_centre_calibrates_from_its_own_pedestrians(
    sessions: sessionmaker[Session], redis_dispatcher: RedisDispatcher, connection: redis.Redis, town_jpeg: bytes
) -> None:
    """The real camera, end to end in the workers: 22 street frames, pose, evidence, a solve, the published truth.

    Oxford Town Centre's published calibration has fx = fy = 2696 px; its ground plane comes from the published
    rotation and translation (bench/towncentre.py). Measured here: fx 2735 px (+1.4 %, 1-sigma 68 px) and the
    normal 1.8 degrees off, from 150 people; the issue's bounds (10 %, 3 degrees) are asserted.
    """
    from bench.towncentre import load_calibration

    truth = load_calibration(TOWN_CENTRE / "TownCentre-calibration-ci.txt")
    for path in sorted((TOWN_CENTRE / "frames").glob("clip_*.jpg")):
        redis_dispatcher.image_stored(CAMERA, store_image(sessions, path.read_bytes()))
    run_jobs(connection)
    redis_dispatcher.request(CALIBRATION_QUEUE, CAMERA, forced=True)  # one last solve on all the evidence
    run_jobs(connection)
    with sessions() as session:
        calibration = current_calibration(session, CAMERA)
        statuses = {status for (status,) in session.query(Frame.status)}
    assert calibration is not None and calibration.people_used >= 100
    assert abs(calibration.fx_px / truth.fx - 1) < 0.10
    normal = np.array([calibration.normal_x, calibration.normal_y, calibration.normal_z])
    assert np.degrees(np.arccos(np.clip(normal @ truth.ground_normal, -1, 1))) < 3.0
    assert statuses == {"done"}  # every frame measured with it


def test_a_calibrated_cameras_frames_are_searched_the_calibrated_way(
    sessions: sessionmaker[Session],
    redis_dispatcher: RedisDispatcher,
    connection: redis.Redis,
    town_jpeg: bytes,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The worker hands the camera's current calibration to the detector: bands at the scale of the people there.

    Before the camera has a calibration its first frame gets the plain pass and bands sized by the people that pass
    found, and its next frame bands sized by the whole standing people the first one stored, planned with the
    plain pass at once; once the published camera is its current calibration, the next frame's plan is exactly the
    one that calibration predicts.
    """
    from bench.towncentre import as_calibration, load_calibration
    from service.calibration.repository import add_calibration
    from service.domain import CalibrationValues
    from service.pose.pipeline import load_pose_estimator
    from service.pose.regions import observed_plan, sizes_from_people

    estimator = load_pose_estimator(get_settings())
    caplog.set_level("INFO")
    first = store_image(sessions, town_jpeg)
    redis_dispatcher.image_stored(CAMERA, first)
    run_jobs(connection)
    uncalibrated = estimator.plan((1920, 1080))
    assert estimator.last_plan[0] == uncalibrated[0] and estimator.last_plan[1:] != uncalibrated[1:]
    assert estimator.last_sizing == "frame's people"

    following = store_image(sessions, town_jpeg, timestamp=datetime(2026, 1, 1, 0, 0, 1, tzinfo=UTC))
    assert jobs.detect_people(str(following)) == DONE
    with sessions() as session:
        stored = session.query(Observation).filter_by(frame_id=first, usable=True).all()
    size_of = sizes_from_people(np.array([person.box_px for person in stored]), (1920, 1080))
    seen = None if size_of is None else observed_plan(size_of, (1920, 1080))
    assert seen and estimator.last_plan == uncalibrated[:1] + seen

    truth = as_calibration(load_calibration(TOWN_CENTRE / "TownCentre-calibration-ci.txt"))
    with sessions() as session, session.begin():
        values = CalibrationValues.from_solution(truth, people_used=100, evidence_count=100)
        add_calibration(session, CAMERA, values, make_current=True)
    second = store_image(sessions, town_jpeg, timestamp=datetime(2026, 1, 1, 0, 0, 2, tzinfo=UTC))
    # The pose job alone answers the frame: it measures its camera's pending frames itself, so an image frame never
    # waits for a turn of the frames queue behind every keypoint camera (that queue's job is still waiting).
    assert jobs.detect_people(str(second)) == DONE
    assert Queue(FRAMES_QUEUE, connection=connection).count == 0
    guided_plan = estimator.plan((1920, 1080), truth)
    assert guided_plan[1:] and guided_plan[1:] != uncalibrated[1:]
    # The stored calibration round-trips through the database: the same bands, scales equal to float rounding.
    assert _rounded(estimator.last_plan) == _rounded(guided_plan)
    sizings = [getattr(record, "sizing", None) for record in caplog.records if hasattr(record, "sizing")]
    assert sizings == ["frame's people", "camera's people", "calibration"]  # what each frame's log line says
    with sessions() as session:
        frame = session.get(Frame, second)
        assert frame is not None and frame.status == "done" and frame.people >= 10  # measured with that camera


def _rounded(plan: list) -> list[tuple[int, int, int, int, float]]:
    return [(region.x0, region.y0, region.x1, region.y1, round(region.scale, 9)) for region in plan]
